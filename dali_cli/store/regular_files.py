"""Only regular files are read: a FIFO, a socket or a device where dali expects a file (a
`velodyne/000001.bin` that is a named pipe, a symbolic link to /dev/zero) would block the read
forever or never end. `check_regular` refuses them, naming the path, before the file is opened;
symbolic links to regular files are followed as before."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from dali_cli.runtime.errors import StageError

_SPECIAL = (
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)


class SpecialFileError(StageError):
    """A FIFO, socket or device where dali reads a file."""


def special_kind(mode: int) -> str | None:
    """What a special file of this st_mode is ('a FIFO (named pipe)'), None for anything else."""
    for test, name in _SPECIAL:
        if test(mode):
            return name
    return None


def check_regular(path: str | Path, what: str = "file") -> Path:
    """`path`, unless it (or what its symbolic link points to) is a FIFO, socket or device:
    SpecialFileError naming it. A missing path passes (the reader says it is missing)."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return path
    kind = special_kind(mode)
    if kind is not None:
        raise SpecialFileError(
            f"{path}: the {what} is {kind}, not a regular file; dali reads only regular files",
            path=str(path),
        )
    return path
