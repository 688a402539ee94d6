"""One file written atomically: into a hidden temporary beside it, then renamed onto it, so a
reader (or a crash) never sees half a file. Whole artifact directories: dali_cli.store.atomic_dir.

The temporary `.<name>.<pid>-<token>.part` is unique per run (a restarted container reuses
pids) and locked (`flock`) while it is written: a temporary of that form that no live process
holds was left by a killed writer, and the next write of `<name>` removes it."""

from __future__ import annotations

import fcntl
import os
import re
import secrets
from collections.abc import Callable
from pathlib import Path

from dali_cli.runtime.errors import WriteError


def _part_pattern(name: str) -> re.Pattern:
    return re.compile(rf"\.{re.escape(name)}\.\d+-[0-9a-f]{{16}}\.part")


def remove_killed_parts(path: Path) -> list[Path]:
    """Delete the temporaries of `path` (exactly `.<name>.<pid>-<token>.part`, regular files)
    no live writer holds locked; returns them."""
    pattern, removed = _part_pattern(path.name), []
    try:
        candidates = [p for p in path.parent.iterdir() if pattern.fullmatch(p.name)]
    except OSError:
        return removed
    for part in candidates:
        try:
            fd = os.open(part, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
        except OSError:
            continue
        try:
            if not os.path.samestat(os.fstat(fd), os.lstat(part)):
                continue
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # a live writer holds it: kept
            part.unlink()
            removed.append(part)
        except OSError:
            continue
        finally:
            os.close(fd)
    return removed


def write_atomically(path: str | Path, write: Callable[[Path], None]) -> Path:
    """`write(temporary)`, then rename the temporary onto `path` (parents created). The
    temporary (`.<name>.<pid>-<token>.part`, same directory, same file system, locked while
    written) is removed when `write` fails; `path` then keeps its previous content. A write
    error (a full disk included) is a WriteError naming `path`."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(8)}.part")
    fd = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_killed_parts(path)
        fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
        fcntl.flock(fd, fcntl.LOCK_EX)
        write(temporary)
        os.replace(temporary, path)
    except OSError as error:
        raise WriteError(path, error) from None
    finally:
        if fd is not None:
            temporary.unlink(missing_ok=True)
            os.close(fd)
    return path


def write_text_atomically(path: str | Path, text: str) -> Path:
    """`text` into `path` (UTF-8), atomically."""
    return write_atomically(path, lambda temporary: temporary.write_text(text, encoding="utf-8"))
