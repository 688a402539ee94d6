"""Engines that run the shards of a per-frame stage: `local` (this machine's process pool, or
in-process for one worker) and `ray` (a Ray cluster, or a local Ray instance).

The contract every stage uses (docs/scale-out.md):
- the stage splits its frames into `Shard`s (contiguous runs of frame indices, `plan_shards`);
- it gives the executor a picklable *worker factory*: every engine process (pool process, Ray
  actor) calls it once, so the detector, or the model library and its BVHs, is loaded once per
  worker; then `worker.run(shard, directory)` for each shard it is handed. The worker writes the
  shard's outputs into `directory` (a fresh folder `<artifact tmp>/shards/<index>`) and returns a
  small picklable summary (counts, seconds): frames never travel back through the engine;
- `Executor.map_shards` yields `(shard, summary)` in shard order, each as soon as it and every
  shard before it are done, so the stage merges shard by shard into the same writers as the serial
  path (identical bytes) and deletes each merged shard: the driver never holds the frame set;
- a shard that still fails after the engine's retries stops the run: `ShardsFailed` names the
  failing frames; run_stage then removes the temporary directory (no artifact is written).
"""

from __future__ import annotations

import errno
import os
import shutil
import socket
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from dali_cli.runtime import console
from dali_cli.runtime.errors import ParameterError, StageError

ENGINES = ("local", "ray")
SHARDS_DIR = "shards"  # inside the artifact's temporary directory; removed before the commit


@dataclass(frozen=True)
class Shard:
    """Frames `start..stop-1` of the stage's frame set (ids `frame_ids`), numbered `index`;
    `payload` is the shard's own small input (e.g. its frames' boxes), picklable."""

    index: int
    start: int
    stop: int
    frame_ids: tuple[str, ...]
    payload: Any = None

    def describe(self) -> str:
        first, last = self.frame_ids[0], self.frame_ids[-1]
        return f"frame '{first}'" if first == last else f"frames '{first}'..'{last}'"


class ShardWorker(Protocol):
    def run(self, shard: Shard, directory: Path) -> dict: ...


class FrameFailed(Exception):
    """A frame (or a batch of frames) a worker could not process; picklable across engines."""

    def __init__(self, frame_ids: tuple[str, ...], message: str):
        super().__init__(frame_ids, message)
        self.frame_ids = tuple(frame_ids)
        self.message = message

    def __str__(self) -> str:
        names = ", ".join(f"'{f}'" for f in self.frame_ids)
        return f"frame{'s' if len(self.frame_ids) > 1 else ''} {names}: {self.message}"


class ShardsFailed(StageError):
    """Shards that failed after the engine's retries; the message names their frames."""

    def __init__(self, engine: str, failures: list[tuple[Shard, str]]):
        lines = [
            f"shard {shard.index} ({shard.describe()}): {problem}" for shard, problem in failures
        ]
        super().__init__(
            f"{engine}: {len(failures)} shard(s) failed, nothing was written:\n  "
            + "\n  ".join(lines)
        )
        self.failures = failures


DISK_REASONS = {code: os.strerror(code) for code in (errno.ENOSPC, errno.EDQUOT, errno.EROFS)}


def disk_error(errors: list[BaseException], directory: Path) -> OSError | None:
    """The write error behind shards that failed writing into `directory`, when it is the
    disk's (full, over quota, read-only; seen through a worker's pickled error or, for a short
    write without an errno, through the disk's free space), else None."""
    from dali_cli.store.disk_space import NEARLY_FULL, DiskSpaceError, free_bytes

    for error in errors:
        code = getattr(error, "errno", None)
        if code in DISK_REASONS:
            return OSError(code, DISK_REASONS[code], getattr(error, "filename", None))
        text = str(error)
        for code, reason in DISK_REASONS.items():
            if reason in text:
                return OSError(code, reason, str(directory))
    if any(isinstance(e, OSError) or "OSError" in str(e) for e in errors):
        free = free_bytes(directory)
        if free is not None and free < NEARLY_FULL:
            return DiskSpaceError(directory, None, free)
    return None


@contextmanager
def naming_frames(*frame_ids: str):
    """Re-raise any error of the block as FrameFailed naming `frame_ids` (a worker wraps each
    frame, or batch, so that a failure names the frames, not just the shard)."""
    try:
        yield
    except FrameFailed:
        raise
    except Exception as error:
        raise FrameFailed(frame_ids, f"{type(error).__name__}: {error}") from error


# ---------------------------------------------------------------------------------------------
# What each worker did (for the logs and the manifest)

_loads: Counter = Counter()


def count_load(what: str) -> None:
    """Record that this process loaded `what` (a detector, a model library): shard summaries
    carry the counts, so a worker that reloads per shard shows up in the manifest (and tests)."""
    _loads[what] += 1


def worker_identity() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def run_shard(worker: ShardWorker, shard: Shard, root: Path) -> dict:
    """Run one shard on an engine's worker (every engine calls this, in the worker's process):
    the worker's summary plus who ran it, its frames, wall and CPU seconds (all threads of the
    process) and the loads of the process so far."""
    wall, cpu = time.perf_counter(), time.process_time()
    summary = worker.run(shard, shard_directory(root, shard))
    return {
        **(summary or {}),
        "worker": worker_identity(),
        "frames": len(shard.frame_ids),
        "seconds": time.perf_counter() - wall,
        "cpu_seconds": time.process_time() - cpu,
        "loads": dict(_loads),
    }


@dataclass
class WorkerRecord:
    shards: int = 0
    frames: int = 0
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    loads: dict = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------
# Shards


def plan_shards(
    frame_ids: list[str],
    workers: int,
    multiple: int = 1,
    max_frames: int = 64,
    per_worker: int = 4,
    payloads: Callable[[int, int], Any] | None = None,
) -> list[Shard]:
    """Contiguous shards of about `per_worker` per worker (load balance), at most `max_frames`
    frames each (bounded worker memory), sizes a multiple of `multiple` (e.g. the detector's
    batch size, so every batch is the serial path's batch). `payloads(start, stop)` gives each
    shard's payload."""
    count = len(frame_ids)
    size = -(-count // max(1, workers * per_worker))
    size = max(
        multiple,
        min(-(-size // multiple) * multiple, max(multiple, max_frames // multiple * multiple)),
    )
    shards = []
    for index, start in enumerate(range(0, count, size)):
        stop = min(start + size, count)
        payload = payloads(start, stop) if payloads is not None else None
        shards.append(Shard(index, start, stop, tuple(frame_ids[start:stop]), payload))
    return shards


# ---------------------------------------------------------------------------------------------
# Executors


class Executor:
    """Runs shards on an engine; use as a context manager (starts / stops the engine)."""

    name = "?"

    def __init__(self, workers: int):
        self.workers = max(1, int(workers))
        self.records: dict[str, WorkerRecord] = {}
        self.started_seconds = 0.0  # engine start-up (Ray: init + actors)

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        pass

    @property
    def serial(self) -> bool:
        """True when shards would run in this very process: the stage's serial path is then the
        same computation without the shard round trip, and stages use it."""
        return False

    def describe(self) -> str:
        return f"{self.name}, {self.workers} worker{'s' if self.workers > 1 else ''}"

    def _completions(
        self, factory: Callable[[], ShardWorker], shards: list[Shard], directory: Path
    ) -> Iterator[tuple[Shard, dict | BaseException]]:
        """(shard, summary or error) in completion order; after `self.stop()` the engine submits
        nothing new and only drains what is running."""
        raise NotImplementedError

    def stop(self) -> None:
        self._stopping = True

    def map_shards(
        self, factory: Callable[[], ShardWorker], shards: list[Shard], directory: Path
    ) -> Iterator[tuple[Shard, dict]]:
        """Run every shard (see the module docstring); yields (shard, summary) in shard order.
        Raises ShardsFailed naming the frames of the shards that failed."""
        self._stopping = False
        done: dict[int, tuple[Shard, dict]] = {}
        failures: list[tuple[Shard, str]] = []
        errors: list[BaseException] = []
        following = 0
        for shard, result in self._completions(factory, shards, directory):
            if isinstance(result, BaseException):
                failures.append((shard, _describe_error(result)))
                errors.append(result)
                self.stop()
                continue
            self._record(result)
            done[shard.index] = (shard, result)
            while not failures and following in done:
                yield done.pop(following)
                following += 1
        if failures:
            disk = disk_error(errors, directory)
            if disk is not None:  # the stage runner names the output: one line, no shard list
                raise disk
            raise ShardsFailed(self.name, sorted(failures, key=lambda item: item[0].index))
        while following in done:  # pragma: no cover - completions always end in order here
            yield done.pop(following)
            following += 1

    def _record(self, summary: dict) -> None:
        record = self.records.setdefault(summary.get("worker", "?"), WorkerRecord())
        record.shards += 1
        record.frames += int(summary.get("frames", 0))
        record.seconds += float(summary.get("seconds", 0.0))
        record.cpu_seconds += float(summary.get("cpu_seconds", 0.0))
        record.loads = dict(summary.get("loads", {}))

    def report(self) -> dict:
        """The engine, its workers and what each did (shards, frames, busy seconds, loads)."""
        return {
            "engine": self.name,
            "workers": self.workers,
            "startup_seconds": round(self.started_seconds, 3),
            "per_worker": {
                worker: {
                    "shards": r.shards,
                    "frames": r.frames,
                    "busy_seconds": round(r.seconds, 3),
                    "cpu_seconds": round(r.cpu_seconds, 3),
                    "loads": r.loads,
                }
                for worker, r in sorted(self.records.items())
            },
        }

    def echo_report(self, stage: str) -> None:
        report = self.report()
        if self.serial:
            console.info(f"{stage}: ran on {report['engine']}, in this process")
            return
        console.info(
            f"{stage}: ran on {report['engine']} with {report['workers']} worker(s)"
            + (
                f" (start-up {report['startup_seconds']:.1f} s)"
                if report["startup_seconds"]
                else ""
            )
        )
        for worker, r in report["per_worker"].items():
            loads = ", ".join(f"{k} x{v}" for k, v in sorted(r["loads"].items())) or "nothing"
            console.info(
                f"  {worker}: {r['shards']} shards, {r['frames']} frames, "
                f"{r['busy_seconds']:.1f} s busy, loaded {loads}"
            )


def _describe_error(error: BaseException) -> str:
    cause = getattr(error, "cause", None)  # Ray wraps the worker's exception (RayTaskError)
    if isinstance(cause, BaseException):
        error = cause
    if isinstance(error, FrameFailed):
        return str(error)
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[-1] if text else ''}"


def make_executor(
    engine: str, workers: int | None, address: str | None = None, cpus_per_worker: int = 1
) -> Executor:
    """The executor of `--executor ENGINE --workers N [--ray-address ADDR]`. workers None: local,
    1; ray, every CPU of the cluster (or of this machine for a local instance)."""
    if engine == "local":
        if address is not None:
            raise ParameterError(
                ("ray_address", "executor"), "a Ray address needs the ray executor"
            )
        from dali_cli.executors.local import LocalExecutor
        from dali_cli.runtime.cores import available_cores

        cores = available_cores()  # more processes would only oversubscribe it, or fork on
        if workers is not None and workers > cores:  # until the machine runs out (100000)
            raise ParameterError(
                "workers",
                f"{workers} worker processes, but this machine lets dali use {cores} cores",
            )
        return LocalExecutor(workers or 1)
    if engine == "ray":
        from dali_cli.executors.ray import RayExecutor

        return RayExecutor(workers, address, cpus_per_worker=cpus_per_worker)
    raise ParameterError("executor", f"must be one of {', '.join(ENGINES)}, got '{engine}'")


def run_on(executor: Executor, stage: str, body: Callable[[Executor], Any]) -> Any:
    """`body(executor)` with the engine started (and stopped after, also on errors), then the
    log of which engine ran, with how many workers, and what each did."""
    with executor:
        result = body(executor)
    executor.echo_report(stage)
    return result


def shard_results(
    executor: Executor,
    factory: Callable[[], ShardWorker],
    shards: list[Shard],
    directory: Path,
) -> Iterator[tuple[Shard, Path, dict]]:
    """Run `shards` on `executor` with shard folders under `directory/shards`; yields
    (shard, its folder, its summary) in shard order as they complete, for the caller to merge.
    A merged shard's folder is deleted when the caller asks for the next one; the shards folder
    goes at the end (also on failure or Ctrl-C)."""
    root = Path(directory) / SHARDS_DIR
    root.mkdir()
    try:
        for shard, summary in executor.map_shards(factory, shards, root):
            shard_dir = root / f"{shard.index:06d}"
            yield shard, shard_dir, summary
            shutil.rmtree(shard_dir)
    finally:
        shutil.rmtree(root, ignore_errors=True)


def shard_directory(root: Path, shard: Shard) -> Path:
    """The shard's fresh folder; its parent must exist (the worker never creates the artifact's
    temporary directory: a missing one means it was removed, or is not on a shared filesystem)."""
    path = Path(root) / f"{shard.index:06d}"
    if not Path(root).is_dir():
        raise FileNotFoundError(
            f"{root} is not visible on {socket.gethostname()}: --out must be on a filesystem "
            "shared by every worker node (or the run was interrupted)"
        )
    if path.exists():  # a retried shard: start afresh
        shutil.rmtree(path)
    path.mkdir()
    return path
