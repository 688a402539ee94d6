"""The ground-truth sampling database of a training set on disk: built once per set (one pass
over its frames, in order), kept in a cache directory keyed by what it is made of (the frame
sets' content hashes, clipping and transforms, the boxes, the region), memory-mapped by every
run and DataLoader worker that uses it.

Layout of one entry, `<cache>/gt_database/<key>/`: boxes.npy (k, 7) float64, offsets.npy
(k + 1,) int64, points.f32 (offsets[-1], 4) float32 raw, database.json (counts, region). An
entry is written into `<key>.tmp-<pid>-<token>` under the entry's lock and renamed into place,
so a reader sees a complete one or none; what a killed build left is removed by the next one
(store.atomic_dir); it is never written inside an input artifact.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from dali_cli.detector.augment import ObjectDatabase, frame_instances
from dali_cli.runtime import console
from dali_cli.runtime.errors import StageError
from dali_cli.store.atomic_dir import (
    OutputLock,
    make_temporary,
    recover_interrupted,
    remove_tree,
    unmark,
)
from dali_cli.store.regular_files import read_json_file

CACHE_ENV = "DALI_CACHE_DIR"  # where caches go instead of beside the training data
FORMAT = 1  # bump when the layout or the instances' selection changes


class MappedDatabase(ObjectDatabase):
    """An ObjectDatabase whose points are memory-mapped from a cache entry; pickled as its path
    (a DataLoader worker maps the file itself instead of receiving a copy)."""

    def __reduce__(self):
        return (load_database, (self.directory,))


def load_database(directory: str | Path) -> MappedDatabase:
    """The database of the cache entry `directory` (points memory-mapped, read-only)."""
    directory = Path(directory)
    meta = read_json_file(directory / "database.json", "gt database index")
    offsets = np.load(directory / "offsets.npy")
    points = (
        np.memmap(directory / "points.f32", np.float32, "r", shape=(int(offsets[-1]), 4))
        if offsets[-1] > 0
        else np.zeros((0, 4), np.float32)
    )
    region = tuple(meta["region"]) if meta["region"] is not None else None
    database = MappedDatabase(np.load(directory / "boxes.npy"), points, offsets, region)
    database.directory = directory
    return database


def cache_root(data_dir: str | Path) -> Path:
    """The cache directory for training data read from `data_dir`: $DALI_CACHE_DIR when set,
        else `.dali-cache` in the directory holding `data_dir`, or the one holding the outermost
    artifact `data_dir` lies in."""
    from dali_cli.store.output_paths import is_dali_artifact

    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    parent = Path(data_dir).resolve().parent
    for ancestor in [parent, *parent.parents]:  # above the outermost artifact holding data_dir
        if is_dali_artifact(ancestor):
            parent = ancestor.parent
    return parent / ".dali-cache"


def first_directory(points) -> Path:
    """The frame set directory the first frames of a FramePoints / ChainedPoints come from."""
    while hasattr(points, "parts"):
        points = points.parts[0]
    return points.directory


def database_key(frames, region, min_points: int) -> str:
    """The cache key of `frames`' (LabeledFrames) database: a hash of its points' identity, its
    boxes, the region and min_points."""
    from dali_cli.detector.data import boxes_hash, points_identity

    document = {
        "format": FORMAT,
        "points": points_identity(frames.points),
        "boxes": boxes_hash(frames.boxes),
        "region": None if region is None else [float(v) for v in region],
        "min_points": int(min_points),
    }
    text = json.dumps(document, sort_keys=True)
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


def cached_database(
    frames, region=None, min_points: int = 5, root: str | Path | None = None
) -> MappedDatabase:
    """`ObjectDatabase.build(frames.points, frames.boxes, min_points, region)`, the same
    instances in the same order, from the cache under `root` (default `cache_root` of the
    frames' directory), built there first when absent (one pass over the frames; memory: one
    frame and the boxes). The entry is built under its lock (a second run building it waits,
    then reuses it) in a marked `<key>.tmp-<pid>-<token>`, then renamed into place."""
    root = Path(root) if root is not None else cache_root(first_directory(frames.points))
    directory = root / "gt_database" / database_key(frames, region, min_points)
    directory.parent.mkdir(parents=True, exist_ok=True)
    remove_abandoned(directory.parent)
    if (directory / "database.json").is_file():
        return load_database(directory)
    with OutputLock(directory, wait=True) as lock:
        recover_interrupted(directory, console.info, lock.inherited)
        if not (directory / "database.json").is_file():  # not built by a run we waited for
            tmp = make_temporary(directory, lock.token)
            try:
                write_database(tmp, frames, region, min_points)
                os.rename(tmp, directory)
            except BaseException:
                remove_tree(tmp)
                raise
            unmark(directory)
            console.info(f"gt database: {directory}")
    return load_database(directory)


def remove_abandoned(folder: Path) -> None:
    """Clean what killed builds left in `folder`: for each entry with a `<key>.tmp-*` or a lock
    file `.<key>.lock` beside it that no live process holds, the leftovers recover_interrupted
    recognizes as dali's (marked, or named with a token its lock file recorded) and the lock
    file. Whatever else has such a name is left as it is; an entry being built is skipped."""
    keys = {path.name.rpartition(".tmp-")[0] for path in folder.glob("*.tmp-*")}
    keys |= {path.name[1 : -len(".lock")] for path in folder.glob(".*.lock")}
    for key in sorted(key for key in keys if key):
        try:
            with OutputLock(folder / key) as lock:
                recover_interrupted(folder / key, console.info, lock.inherited)
        except StageError:  # being built (busy), or a lock file that is not dali's
            continue


def write_database(directory: Path, frames, region, min_points: int) -> None:
    """Write the entry's files into `directory` (see the module), frame by frame."""
    boxes, sizes = [], [0]
    with open(directory / "points.f32", "wb") as stream:
        for points, frame_boxes in zip(frames.points, frames.boxes, strict=True):
            kept_boxes, kept_points = frame_instances(points, frame_boxes, min_points, region)
            boxes.extend(kept_boxes)
            for instance in kept_points:
                stream.write(np.ascontiguousarray(instance, np.float32).tobytes())
                sizes.append(len(instance))
    np.save(directory / "boxes.npy", np.asarray(boxes, np.float64).reshape(-1, 7))
    np.save(directory / "offsets.npy", np.cumsum(sizes).astype(np.int64))
    meta = {
        "instances": len(boxes),
        "points": int(sum(sizes)),
        "region": None if region is None else [float(v) for v in region],
        "min_points": int(min_points),
        "frames": len(frames.boxes),
    }
    (directory / "database.json").write_text(json.dumps(meta, indent=1))
