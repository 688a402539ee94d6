"""Run RC or CF over a whole frame set, in order, on one process or several.

Each frame depends only on its points, its boxes (in table order) and the run seed, so the output
is the same for any number of workers. Workers are spawned processes (no fork after Zarr has
started its threads); each loads the model library once and builds a model's BVH on first use.
Frames without boxes pass through without any ray casting.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from dali_cli.ppcg.cf import CfParams, cf_frame
from dali_cli.ppcg.frame import BoxRecords
from dali_cli.ppcg.models import ModelBank
from dali_cli.ppcg.rc import RcParams, rc_frame

_CHUNK_FRAMES = 16  # frames per worker task


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
        from dali_cli.artifacts import FrameSet
        from dali_cli.sensors import get_profile

        self.job = job
        self.frames = FrameSet(job.target_dir)
        self.profile = get_profile(job.sensor, job.sensors_path)
        if bank is None:
            from dali_cli.library import read_library

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


_state: _Worker | None = None


def _init_worker(job: Job) -> None:
    global _state
    _state = _Worker(job)


def _run_chunk(task: tuple[list[int], list[np.ndarray]]) -> list[FrameResult]:
    return list(_state.run(*task))


def run_frames(
    job: Job,
    boxes_by_frame: list[np.ndarray],
    workers: int = 1,
    bank: ModelBank | None = None,
) -> Iterator[FrameResult]:
    """Process every frame of `job.target_dir` in order; boxes_by_frame[i] `(k_i, 7)` are frame
    i's boxes. Yields FrameResults in frame order. `bank` (single process only) skips reading
    the library, for tests."""
    count = len(boxes_by_frame)
    if workers <= 1:
        worker = _Worker(job, bank)
        if len(worker.frames) != count:
            raise ValueError(f"{count} box lists for {len(worker.frames)} frames")
        yield from worker.run(None, boxes_by_frame)
        return
    from dali_cli.workers import process_pool

    chunks = [list(range(a, min(a + _CHUNK_FRAMES, count))) for a in range(0, count, _CHUNK_FRAMES)]
    tasks = [(chunk, [boxes_by_frame[i] for i in chunk]) for chunk in chunks]
    with process_pool(workers, _init_worker, (job,)) as pool:
        pending = deque()
        for task in tasks:  # at most 2 chunks per worker in flight bounds the memory held
            pending.append(pool.submit(_run_chunk, task))
            if len(pending) >= 2 * workers:
                yield from pending.popleft().result()
        while pending:
            yield from pending.popleft().result()
