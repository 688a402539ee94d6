"""Run RC or CF over a whole frame set, in order, in this process or as shards on an executor
(dali_cli.executors: a local process pool or Ray actors).

Each frame depends only on its points, its boxes (in table order) and the run seed, so the output
is the same for any number of workers and any engine. Each worker loads the model library once
and builds a model's BVH on first use. Frames without boxes pass through without any ray casting.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from dali_cli.ppcg.cf import CfParams, cf_frame
from dali_cli.ppcg.frame import BoxRecords
from dali_cli.ppcg.models import ModelBank
from dali_cli.ppcg.rc import RcParams, rc_frame

_CHUNK_FRAMES = 16  # at most this many frames per shard


@dataclass(frozen=True)
class Job:
    """Everything a worker needs, picklable: mode "rc" or "cf", paths, model kind, params."""

    mode: str
    target_dir: str
    library_dir: str
    models: str
    sensor: str
    sensors_path: str | None
    params: RcParams | CfParams


@dataclass
class FrameResult:
    """One processed frame: new points `(n', 4)` float32, per-box records, compute seconds and
    the seconds spent reading it (blocks of frames are read at once: the first frame of a block
    carries the block's read time)."""

    frame_id: str
    points: np.ndarray
    records: BoxRecords
    seconds: float
    read_seconds: float = 0.0


class _Worker:
    """Per-process state: the frame set, the model bank and the sensor profile."""

    def __init__(self, job: Job, bank: ModelBank | None = None):
        from dali_cli.sensors import get_profile
        from dali_cli.store.artifacts import FrameSet

        self.job = job
        self.frames = FrameSet(job.target_dir)
        self.profile = get_profile(job.sensor, job.sensors_path)
        if bank is None:
            from dali_cli.executors import count_load
            from dali_cli.library import read_library

            count_load("model library")
            bank = ModelBank.from_library(
                read_library(job.library_dir), job.models, job.library_dir
            )
        self.bank = bank

    def process(self, frame_id: str, points: np.ndarray, boxes: np.ndarray) -> FrameResult:
        started = time.perf_counter()
        if len(boxes) == 0:
            records = BoxRecords.raw(np.zeros(0, np.int32))
            return FrameResult(frame_id, points, records, time.perf_counter() - started)
        if self.job.mode == "rc":
            new, records = rc_frame(frame_id, points, boxes, self.bank, self.job.params)
        else:
            new, records = cf_frame(
                frame_id, points, boxes, self.bank, self.profile, self.job.params
            )
        return FrameResult(frame_id, new, records, time.perf_counter() - started)

    def run(self, indices: list[int] | None, boxes: list[np.ndarray]) -> Iterator[FrameResult]:
        frames = self.frames.iter_frames(indices)
        for frame_boxes in boxes:
            started = time.perf_counter()
            frame_id, points = next(frames)
            read = time.perf_counter() - started
            result = self.process(frame_id, points, frame_boxes)
            result.read_seconds = read
            yield result


@dataclass(frozen=True)
class PpcgShards:
    """Worker factory of the sharded path: each engine worker makes one (loading the model
    library once) and runs shards of frames; a shard's payload is its frames' boxes."""

    job: Job

    def __call__(self) -> PpcgShards:
        return _ShardWorker(_Worker(self.job))


class _ShardWorker:
    def __init__(self, state: _Worker):
        self.state = state

    def run(self, shard, directory: Path) -> dict:
        """The shard's new frames (shard files) and records.npz: every BoxRecords field
        concatenated over its frames, the boxes per frame, compute and read seconds."""
        from dali_cli.executors import naming_frames
        from dali_cli.executors.shards import ShardFramesWriter

        writer = ShardFramesWriter(directory)
        results = self.state.run(list(range(shard.start, shard.stop)), list(shard.payload))
        columns: dict[str, list] = {f.name: [] for f in fields(BoxRecords)}
        boxes, seconds, reads = [], [], []
        for frame_id in shard.frame_ids:
            with naming_frames(frame_id):
                result = next(results)
            writer.append(result.frame_id, result.points)
            for name, values in columns.items():
                values.append(getattr(result.records, name))
            boxes.append(len(result.records.ppcg))
            seconds.append(result.seconds)
            reads.append(result.read_seconds)
        writer.close()
        arrays = {
            name: _stored(np.concatenate(values)) if values else np.zeros(0)
            for name, values in columns.items()
        }
        np.savez(directory / "records.npz", boxes=boxes, seconds=seconds, reads=reads, **arrays)
        return {}


def _stored(values: np.ndarray) -> np.ndarray:
    """Object (string) columns as fixed-width unicode: npz then needs no pickle."""
    return values.astype(str) if values.dtype == object else values


def _read_shard(directory: Path) -> Iterator[FrameResult]:
    """The FrameResults of a shard the _ShardWorker wrote, in order."""
    from dali_cli.executors.shards import read_shard_frames

    with np.load(directory / "records.npz") as stored:
        data = {name: stored[name] for name in stored.files}
    ends = np.cumsum(data["boxes"])
    starts = ends - data["boxes"]
    for i, (frame_id, points) in enumerate(read_shard_frames(directory)):
        part = slice(int(starts[i]), int(ends[i]))
        records = BoxRecords(
            **{
                f.name: data[f.name][part].astype(object)
                if data[f.name].dtype.kind == "U"
                else data[f.name][part]
                for f in fields(BoxRecords)
            }
        )
        yield FrameResult(
            frame_id, points, records, float(data["seconds"][i]), float(data["reads"][i])
        )


def run_frames(
    job: Job,
    boxes_by_frame: list[np.ndarray],
    executor=None,
    bank: ModelBank | None = None,
    directory: Path | None = None,
) -> Iterator[FrameResult]:
    """Process every frame of `job.target_dir` in order; boxes_by_frame[i] `(k_i, 7)` are frame
    i's boxes. Yields FrameResults in frame order. In this process when `executor` is None or
    serial (`bank`, for tests, then replaces the library), else as shards on the executor's
    workers, written under `directory` (the artifact's temporary directory)."""
    count = len(boxes_by_frame)
    if executor is None or executor.serial:
        worker = _Worker(job, bank)
        if len(worker.frames) != count:
            raise ValueError(f"{count} box lists for {len(worker.frames)} frames")
        yield from worker.run(None, boxes_by_frame)
        return
    from dali_cli.executors import plan_shards, shard_results
    from dali_cli.store.artifacts import FrameSet

    frame_ids = FrameSet(job.target_dir).frame_ids
    if len(frame_ids) != count:
        raise ValueError(f"{count} box lists for {len(frame_ids)} frames")
    shards = plan_shards(
        frame_ids,
        executor.workers,
        max_frames=_CHUNK_FRAMES,
        payloads=lambda start, stop: boxes_by_frame[start:stop],
    )
    for _, shard_dir, _ in shard_results(executor, PpcgShards(job), shards, directory):
        yield from _read_shard(shard_dir)
