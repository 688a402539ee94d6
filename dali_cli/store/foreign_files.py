"""Which files inside an artifact its stage did not write (docs/data-safety.md, "What dali
writes"): a stage never deletes a file it did not write, so a rerun over an artifact holding
such a file (`notes.txt` a user put there) stops and names it.

The manifest does not list file names; it records the content hash of the files the stage
wrote (names and digests) and their count. An intact artifact matches its hash: every file is
the stage's. Otherwise the files changed after the manifest was written (ctime, which no user
can set back) are the candidates: when leaving them out restores the recorded hash, they are
exactly the added files; when it does not, and the artifact holds more files than the stage
wrote, some of them were added and cannot be told from edited ones, so all of them are named.
Fewer or as many files as recorded, none proven added: the stage's own files were edited or
removed, and the rerun rebuilds them as before.
"""

from __future__ import annotations

from pathlib import Path

from dali_cli.store.file_hashes import tree_digest, tree_files


def foreign_files(
    out: Path, manifest: dict, exclude: tuple[str, ...], hash_method: str
) -> list[str]:
    """Relative names of the files in the artifact `out` (whose manifest is `manifest`) that
    its stage did not write; `exclude`: names outside its content hash (the manifest itself,
    files other commands may add). `hash_method`: the hashing this dali uses (a manifest of
    another one never matches, and only the file count and times decide)."""
    files = {name: path for name, path in tree_files(out).items() if name not in exclude}
    recorded = manifest.get("content_hash") if manifest.get("hash_method") == hash_method else None

    def matches(names: dict[str, Path]) -> bool:
        return recorded is not None and tree_digest(list(names.items())) == recorded

    if matches(files):
        return []
    written = out / "manifest.json"
    try:
        written_ns = written.stat().st_ctime_ns
    except OSError:
        return []
    newer = [name for name, path in files.items() if path.stat().st_ctime_ns > written_ns]
    if newer and matches({n: p for n, p in files.items() if n not in newer}):
        return newer
    count = (manifest.get("outputs") or {}).get("files")
    if isinstance(count, int) and not isinstance(count, bool) and len(files) <= count:
        return []
    return newer
