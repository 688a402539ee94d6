"""Content hashes of files and artifact trees, cached per file.

A stage decides whether it is up to date from the hashes of its inputs' *files* (never from a
hash an input's manifest claims: a hand-edited boxes.parquet under an unchanged manifest must
make its consumers stale). Hashing gigabytes on every run would be slow, so each file's digest
is cached under its identity on disk: (device, inode, size, mtime_ns, ctime_ns). Any write to a
file changes its mtime and ctime, and ctime cannot be set back by a user (`touch -d` only sets
mtime), so a cached digest is reused only for the very same bytes. Renaming a directory (as the
stage runner does when it commits an artifact) keeps its files' identities, so an artifact's
files hashed while it was built are not hashed again when the next stage reads it.

The cache is one SQLite file under `$DALI_CACHE_DIR`, else `$XDG_CACHE_HOME/dali`, else
`~/.cache/dali`. When it cannot be opened or written (read-only home, ...), hashing still works,
uncached.
"""

from __future__ import annotations

import hashlib
import os
import sqlite3
from pathlib import Path

from dali_cli.store.regular_files import check_regular

HASH_BLOCK = 1 << 22
CACHE_NAME = "file_hashes.sqlite"


def cache_path() -> Path:
    """Where the digest cache lives (see module docstring)."""
    explicit = os.environ.get("DALI_CACHE_DIR")
    if explicit:
        return Path(explicit) / CACHE_NAME
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "dali" / CACHE_NAME


class _DigestCache:
    """file identity → hex digest, in SQLite; silently disabled when unusable."""

    def __init__(self) -> None:
        self._connection: sqlite3.Connection | None = None
        self._path: Path | None = None
        self._disabled = False

    def _open(self) -> sqlite3.Connection | None:
        path = cache_path()
        if self._connection is not None and path == self._path:
            return self._connection
        if self._disabled and path == self._path:
            return None
        self._path, self._connection, self._disabled = path, None, False
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            connection = sqlite3.connect(path, timeout=30, isolation_level=None)
            connection.execute(
                "CREATE TABLE IF NOT EXISTS digests (identity TEXT PRIMARY KEY, digest TEXT)"
            )
        except (OSError, sqlite3.Error):
            self._disabled = True
            return None
        self._connection = connection
        return connection

    def get(self, identity: str) -> str | None:
        connection = self._open()
        if connection is None:
            return None
        try:
            row = connection.execute(
                "SELECT digest FROM digests WHERE identity = ?", (identity,)
            ).fetchone()
        except sqlite3.Error:
            return None
        return row[0] if row else None

    def put(self, identity: str, digest: str) -> None:
        connection = self._open()
        if connection is None:
            return
        try:
            connection.execute(
                "INSERT OR REPLACE INTO digests (identity, digest) VALUES (?, ?)",
                (identity, digest),
            )
        except sqlite3.Error:
            pass


_CACHE = _DigestCache()


def file_identity(stat: os.stat_result) -> str:
    """What identifies one version of a file's bytes on this machine."""
    return f"{stat.st_dev}:{stat.st_ino}:{stat.st_size}:{stat.st_mtime_ns}:{stat.st_ctime_ns}"


def file_digest(path: str | Path) -> str:
    """blake2b-128 hex digest of a file's bytes, cached by the file's identity."""
    path = Path(path)
    before = path.stat()
    identity = file_identity(before)
    cached = _CACHE.get(identity)
    if cached is not None:
        return cached
    digest = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as handle:
        while block := handle.read(HASH_BLOCK):
            digest.update(block)
    value = digest.hexdigest()
    if file_identity(path.stat()) == identity:  # not written to while we read it
        _CACHE.put(identity, value)
    return value


def hash_tree(path: str | Path, exclude: tuple[str, ...] = ()) -> str:
    """Digest of every file under `path` (relative names and file digests, sorted by name); a
    file works too (its own digest, under its name). Names in `exclude` are left out."""
    path = check_regular(Path(path))
    if path.is_file():
        return tree_digest([(path.name, path)])
    return tree_digest([(r, f) for r, f in tree_files(path).items() if r not in exclude])


def tree_files(directory: Path) -> dict[str, Path]:
    """Every file under `directory` by its relative name (POSIX), in hash_tree's order (sorted
    as paths, part by part: not the order of the names as strings); a FIFO, socket or
    device inside is refused (SpecialFileError naming it): it would block or never end a
    reader."""
    files = sorted(p for p in directory.rglob("*") if check_regular(p).is_file())
    return {file.relative_to(directory).as_posix(): file for file in files}


def tree_digest(files: list[tuple[str, Path]]) -> str:
    """The digest `hash_tree` gives a tree of these (relative name, path) files, taken in the
    order given (tree_files')."""
    digest = hashlib.blake2b(digest_size=16)
    for relative, file in files:
        digest.update(relative.encode())
        digest.update(b"\0")
        digest.update(file_digest(file).encode())
        digest.update(b"\1")
    return digest.hexdigest()
