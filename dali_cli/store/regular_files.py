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


# ---------------------------------------------------------------------------------------------
# One way to read a file: regular files only, opened non-blocking, a size budget per kind checked
# by stat before a byte is read, text decoded and JSON parsed with a clear error

MiB = 1 << 20
# kind -> bytes a file of that kind may hold (what dali writes is far below; a user's files too)
BUDGETS: dict[str, int] = {
    "json": 16 * MiB,  # model.json, scale.json, manifests, metrics (a metrics.json is ~1 MiB)
    "toml": 4 * MiB,  # sensors.toml
    "label": 4 * MiB,  # one KITTI label_2 file (a frame's objects: a few kB)
    "calib": 1 * MiB,  # one KITTI calib file (about 1 kB)
    "ids": 64 * MiB,  # an id list (a million ids)
    "xml": 256 * MiB,  # a KITTI raw drive's tracklet_labels.xml (a long drive: tens of MB)
    "dataset_json": 2 << 30,  # a dataset's own JSON table (nuScenes' sample_data.json: ~1 GB)
    "table": 1 << 30,  # a Parquet box table or sequence table
    "weights": 2 << 30,  # model.pt
}
MAX_JSON_DEPTH = 64  # what dali writes nests 6 deep
# the files an artifact directory holds at its top, by name: (what a message calls it, kind)
ARTIFACT_FILES: dict[str, tuple[str, str]] = {
    "model.json": ("model description", "json"),
    "scale.json": ("scale file", "json"),
    "manifest.json": ("manifest", "json"),
    "card.json": ("model card", "json"),
    "summary.json": ("summary", "json"),
    "metrics.json": ("metrics file", "json"),
    "model.pt": ("dali model weights", "weights"),
    "boxes.parquet": ("box table", "table"),
    "sequence.parquet": ("sequence table", "table"),
}


class UnreadableFileError(StageError):
    """A file that is not a regular file, too large for its kind, or not text or JSON."""


def checked_size(path: str | Path, what: str, kind: str) -> int:
    """The size of `path` after the checks every read makes (before a byte is read): it exists,
    is a regular file (not a directory, FIFO, socket, device or dangling link) and holds at most
    BUDGETS[kind] bytes. UnreadableFileError naming the file otherwise."""
    path = Path(path)
    try:
        info = os.stat(path)
    except FileNotFoundError:
        dangling = " (a symbolic link to nothing)" if path.is_symlink() else ""
        raise UnreadableFileError(f"{path}: {what} not found{dangling}") from None
    except OSError as error:
        raise UnreadableFileError(f"{path}: cannot read the {what} ({error.strerror})") from None
    if stat.S_ISDIR(info.st_mode):
        raise UnreadableFileError(f"{path}: the {what} is a directory, not a file")
    kind_name = special_kind(info.st_mode)
    if kind_name is not None:
        raise SpecialFileError(
            f"{path}: the {what} is {kind_name}, not a regular file; dali reads only regular files",
            path=str(path),
        )
    budget = BUDGETS[kind]
    if info.st_size > budget:
        raise UnreadableFileError(
            f"{path}: the {what} is {info.st_size:,} bytes, more than the {budget:,} a {kind} "
            "file may hold; not read"
        )
    return info.st_size


def read_file_bytes(path: str | Path, what: str, kind: str) -> bytes:
    """The bytes of a regular file within its kind's budget (see checked_size), opened
    non-blocking so that a file swapped for a FIFO after the check cannot block the read."""
    checked_size(path, what, kind)
    budget = BUDGETS[kind]
    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as error:
        raise UnreadableFileError(f"{path}: cannot open the {what} ({error.strerror})") from None
    try:
        if not stat.S_ISREG(os.fstat(descriptor).st_mode):  # replaced since the check
            raise UnreadableFileError(f"{path}: the {what} is not a regular file")
        with os.fdopen(descriptor, "rb", closefd=False) as handle:
            data = handle.read(budget + 1)
    finally:
        os.close(descriptor)
    if len(data) > budget:
        raise UnreadableFileError(f"{path}: the {what} grew beyond {budget:,} bytes while read")
    return data


def read_text_file(path: str | Path, what: str, kind: str) -> str:
    """The UTF-8 text of a regular file within its kind's budget; UnreadableFileError naming
    the file and the byte offset where it is not UTF-8 text."""
    data = read_file_bytes(path, what, kind)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise UnreadableFileError(
            f"{path}: the {what} is not UTF-8 text (byte {error.start} is {data[error.start]:#04x})"
        ) from None


def json_depth_exceeds(value, limit: int) -> bool:
    """Whether `value` (parsed JSON) nests deeper than `limit` lists and objects."""
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, dict | list):
            if depth > limit:
                return True
            children = item.values() if isinstance(item, dict) else item
            stack.extend((child, depth + 1) for child in children if isinstance(child, dict | list))
    return False


def parse_json_text(text: str, where: str, what: str = "JSON file"):
    """JSON `text` parsed with a depth limit (MAX_JSON_DEPTH); UnreadableFileError naming
    `where` otherwise (NaN and Infinity parse: the value checks of each reader refuse them)."""
    import json

    try:
        value = json.loads(text)
    except RecursionError:
        value = None
        deep = True
    except ValueError as error:  # json.JSONDecodeError is a ValueError
        raise UnreadableFileError(f"{where}: the {what} is not valid JSON ({error})") from None
    else:
        deep = json_depth_exceeds(value, MAX_JSON_DEPTH)
    if deep:
        raise UnreadableFileError(
            f"{where}: the {what} nests deeper than {MAX_JSON_DEPTH} levels; not a file dali wrote"
        )
    return value


def read_json_file(path: str | Path, what: str = "JSON file", kind: str = "json"):
    """A regular file's JSON document, within the budget, parsed with a depth limit."""
    return parse_json_text(read_text_file(path, what, kind), str(path), what)


def check_present_files(paths: list[Path], what: str, kind: str) -> None:
    """Every present file of `paths` held to `kind` (checked_size: a stat each) before a stage
    hashes or reads them; missing files are named where they are read."""
    for path in paths:
        if os.path.lexists(path):
            checked_size(path, what, kind)


def check_artifact_files(directory: str | Path) -> None:
    """The files of ARTIFACT_FILES at the top of `directory`, where present, held to their
    kinds (checked_size) before anything reads or hashes the directory: a 4 GiB model.json is
    refused by its size, not after hashing it."""
    directory = Path(directory)
    if not directory.is_dir():
        return
    for name, (what, kind) in ARTIFACT_FILES.items():
        check_present_files([directory / name], what, kind)


ZARR_META = "zarr.json"
ITEM_BYTES = {"float32": 4, "float64": 8, "int64": 8, "int32": 4, "uint8": 1}
CODEC_SLACK_BYTES = 4096  # a chunk's checksum and codec headers beyond its raw payload


def check_zarr_files(root: str | Path) -> None:
    """Every file of the Zarr group at `root` before zarr opens one: a regular file (no FIFO,
    device or dangling link that would block or never end), each zarr.json valid JSON within the
    JSON budget and depth, each chunk no larger than its array's chunk shape holds (plus codec
    slack; arrays of strings: the table budget). UnreadableFileError naming the file otherwise."""
    root = Path(root)
    budgets: dict[Path, int] = {}
    for directory, _, files in os.walk(root):
        here = Path(directory)
        if ZARR_META in files:
            meta = read_json_file(here / ZARR_META, "Zarr metadata")
            budgets[here] = chunk_budget(meta)
        for name in files:
            if name == ZARR_META:
                continue
            array = next((a for a in (here, *here.parents) if a in budgets), None)
            size = checked_size(here / name, "Zarr chunk", "table")
            if array is not None and size > budgets[array]:
                raise UnreadableFileError(
                    f"{here / name}: the Zarr chunk is {size:,} bytes, more than its array's "
                    f"chunks hold ({budgets[array]:,}); not read"
                )


def chunk_budget(meta) -> int:
    """Bytes one chunk of the array described by `meta` (a zarr.json document) may take."""
    try:
        shape = meta["chunk_grid"]["configuration"]["chunk_shape"]
        item = ITEM_BYTES.get(str(meta["data_type"]))
        count = 1
        for size in shape:
            count *= int(size)
    except (KeyError, TypeError, ValueError):
        return BUDGETS["table"]
    return BUDGETS["table"] if item is None else count * item + CODEC_SLACK_BYTES
