"""Names that come from data (frame ids, sequence names, split names) and the paths built from them.

Frame ids end up in file names (`export kitti` writes `OUT/data/<id>.txt`, `export openpcdet`
`OUT/points/<id>.npy`), so every id is checked once where data enters dali (importers, id lists,
FrameSetWriter, FrameSet, box tables) by `name_problem`, and every writer that builds a path from
one goes through `child_path`, which refuses a path outside its directory whatever the id.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

from dali_cli.runtime.errors import StageError

# NAME_MAX is 255 bytes on Linux/macOS file systems; writers add suffixes such as ".txt" or
# ".npy" (and temp names), so ids keep a margin below it.
MAX_NAME_BYTES = 200
# C0 and C1 control characters and DEL: never part of a dataset's frame id, and NUL truncates paths
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")
_SEPARATORS = ("/", "\\")


class FrameIdError(StageError, ValueError):
    """A name from data that cannot be a frame id; the message says where it came from and why.

    Both a ClickException (a clean CLI error, exit 1) and a ValueError (what the writers raise
    for other malformed frames)."""


def name_problem(name: object) -> str | None:
    """Why `name` cannot be a frame id (a file name component), or None when it can.

    Refused: non-strings, the empty string, `.` and `..`, path separators (`/`, `\\`), control
    characters (U+0000-U+001F, U+007F-U+009F), and more than MAX_NAME_BYTES bytes of UTF-8.
    """
    if not isinstance(name, str):
        return f"is a {type(name).__name__}, not a string"
    if not name:
        return "is empty"
    if name in (".", ".."):
        return f"is {name!r}, a directory reference"
    for separator in _SEPARATORS:
        if separator in name:
            return f"{name!r} contains a path separator {separator!r}"
    control = _CONTROL.search(name)
    if control:
        return f"{name!r} contains the control character {control.group()!r}"
    size = len(name.encode("utf-8", errors="surrogatepass"))
    if size > MAX_NAME_BYTES:
        return f"{name[:40]!r}... is {size} bytes long (at most {MAX_NAME_BYTES})"
    return None


def first_bad_name(names: Iterable[object]) -> tuple[int, str] | None:
    """(position, problem) of the first name that cannot be a frame id, or None if all can."""
    for position, name in enumerate(names):
        problem = name_problem(name)
        if problem is not None:
            return position, problem
    return None


def check_name(name: object, where: str, kind: str = "frame id") -> str:
    """`name` if it can be a frame id, else FrameIdError `"<where>: <kind> <problem>"`; `where`
    names the file and the row or line the name came from."""
    problem = name_problem(name)
    if problem is not None:
        raise FrameIdError(f"{where}: {kind} {problem}")
    return name  # type: ignore[return-value]


def check_names(names: Iterable[object], where: str, unit: str = "row", kind: str = "frame id"):
    """Check many names; the error names `where`, the unit (row, line, record) and its position
    (0-based rows, as in the box table)."""
    bad = first_bad_name(names)
    if bad is not None:
        position, problem = bad
        raise FrameIdError(f"{where}, {unit} {position}: {kind} {problem}")


def child_path(directory: str | Path, name: str, suffix: str = "") -> Path:
    """`directory / (name + suffix)`, refused (ValueError) unless it lies directly inside
    `directory` once both are resolved (FrameIdError): the second, independent guard of every
    writer that names a file after data (the first is `check_name` where the data entered)."""
    directory = Path(directory)
    check_name(name, f"{directory}: refusing to write a file named after", kind="frame id")
    path = directory / f"{name}{suffix}"
    if path.resolve().parent != directory.resolve():
        raise FrameIdError(f"{directory}: '{name}{suffix}' would be written outside {directory}")
    return path
