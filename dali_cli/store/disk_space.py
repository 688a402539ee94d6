"""Disk space: what a full disk looks like to dali, the check a stage makes before it writes
something large, and torch.save made to fail like any other write (docs/data-safety.md).

A full disk, a quota or a read-only file system is an OSError (ENOSPC, EDQUOT, EROFS) that the
stage runner turns into one line naming the output (runtime.errors.WriteError). torch.save
raises RuntimeError instead ("[enforce fail at inline_container.cc] unexpected pos ..."), which
`save_torch` turns into that OSError, with the bytes the file needed.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

FULL = (errno.ENOSPC, errno.EDQUOT)
# below this many free bytes a failed torch.save is taken for a full disk
NEARLY_FULL = 1 << 20


class DiskSpaceError(OSError):
    """No room for a file: `needed` bytes (None when unknown), `free` bytes where it goes."""

    def __init__(self, path, needed: int | None, free: int | None, code: int = errno.ENOSPC):
        super().__init__(code, os.strerror(code), str(path))
        self.needed = needed
        self.free = free


def free_bytes(path: str | Path) -> int | None:
    """Bytes an unprivileged writer may still use on the file system of `path` (its nearest
    existing ancestor), None when unknown."""
    path = Path(path).absolute()
    for candidate in [path, *path.parents]:
        try:
            info = os.statvfs(candidate)
        except (FileNotFoundError, NotADirectoryError):
            continue
        except OSError:
            return None
        return info.f_bavail * info.f_frsize
    return None


def require_free(path: str | Path, needed: int) -> None:
    """DiskSpaceError naming `path` when its file system has fewer than `needed` bytes free."""
    free = free_bytes(path)
    if free is not None and free < needed:
        raise DiskSpaceError(path, needed, free)


def tensor_bytes(value) -> int:
    """Bytes of the tensors and arrays in `value` (dicts, lists, tuples nested): what a file
    holding it needs at least."""
    if isinstance(value, dict):
        return sum(tensor_bytes(item) for item in value.values())
    if isinstance(value, list | tuple):
        return sum(tensor_bytes(item) for item in value)
    if hasattr(value, "element_size") and hasattr(value, "numel"):
        return int(value.element_size() * value.numel())
    return int(getattr(value, "nbytes", 0) or 0)


def save_torch(value, path: str | Path) -> None:
    """torch.save(value, path); a failure of torch's file writer (RuntimeError) is an OSError
    naming `path`: DiskSpaceError with the bytes it needed when the disk is (nearly) full,
    EIO otherwise. The partial file is removed."""
    import torch

    path = Path(path)
    try:
        torch.save(value, path)
    except RuntimeError as error:
        path.unlink(missing_ok=True)
        free = free_bytes(path.parent)
        needed = tensor_bytes(value)
        if free is not None and free < max(NEARLY_FULL, needed):
            raise DiskSpaceError(path, needed, free) from None
        first = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise OSError(
            errno.EIO, f"torch could not write the file ({first[:160]})", str(path)
        ) from None
