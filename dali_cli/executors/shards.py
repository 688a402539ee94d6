"""A shard's frames on disk, between the worker that made them and the driver that merges them
into the artifact's FrameSetWriter (so the merged frames.zarr is the serial run's, byte for byte).

`<shard>/points.npy` float32 (N, 4), `<shard>/offsets.npy` int64 (F + 1,), `<shard>/frame_ids.json`
(F ids): the FrameSet layout without chunking or compression (a shard is read once, at once).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from dali_cli.store.regular_files import read_json_file


class ShardFramesWriter:
    """Collect one shard's frames `(n_i, 4)` float32 and write them with `close()`."""

    def __init__(self, directory: Path):
        self.directory = Path(directory)
        self._ids: list[str] = []
        self._points: list[np.ndarray] = []

    def append(self, frame_id: str, points: np.ndarray) -> None:
        self._ids.append(str(frame_id))
        self._points.append(np.asarray(points, np.float32).reshape(-1, 4))

    def close(self) -> int:
        """Write the shard; returns its number of points."""
        sizes = [len(p) for p in self._points]
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        points = np.concatenate(self._points) if self._points else np.zeros((0, 4), np.float32)
        np.save(self.directory / "points.npy", points)
        np.save(self.directory / "offsets.npy", offsets)
        (self.directory / "frame_ids.json").write_text(json.dumps(self._ids))
        self._points = []
        return int(offsets[-1])


def read_shard_frames(directory: Path) -> Iterator[tuple[str, np.ndarray]]:
    """(frame_id, points `(n, 4)` float32) of a shard in order (memory-mapped)."""
    directory = Path(directory)
    points = np.load(directory / "points.npy", mmap_mode="r")
    offsets = np.load(directory / "offsets.npy")
    ids = read_json_file(directory / "frame_ids.json", "shard frame ids")
    if len(ids) != len(offsets) - 1 or offsets[-1] != len(points):
        raise ValueError(
            f"{directory}: shard files disagree ({len(ids)} ids, {len(offsets) - 1} frames)"
        )
    for index, frame_id in enumerate(ids):
        yield frame_id, np.asarray(points[offsets[index] : offsets[index + 1]])
