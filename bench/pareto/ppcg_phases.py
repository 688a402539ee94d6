"""Where a PPCG frame's time goes, and the floor it cannot go below.

`Phases` wraps the functions the PPCG frame loop calls (reading, in-box tests, model selection,
ray set-up, Embree, assembling the new frame, writing) and sums their seconds per phase; what is
left of the frame loop is bookkeeping. `Floor` measures, on the same frames, what any
implementation of the stage has to pay per frame:

    read   the input chunk files' bytes, their CRC-32C checked and decoded (zstd when the
           artifact is compressed), no Zarr machinery
    embree exactly the Embree calls the stage made (recorded while it ran), replayed bare on the
           cached BVHs
    write  the output points' bytes plus their CRC-32C, written as raw chunk files

Only the Embree part depends on the stage's rays; read and write are bytes in, bytes out.
"""

from __future__ import annotations

import json
import tempfile
import time
from contextlib import ExitStack, contextmanager
from pathlib import Path

import numpy as np

# (phase, module path, owner attribute or None, function name)
_WRAPPED = (
    ("read", "dali_cli.store.artifacts", "FrameSet", "_read_points"),
    ("read", "dali_cli.store.artifacts", "FrameSet", "_checked"),
    ("points_in_boxes", "dali_cli.ppcg.rc", None, "car_points"),
    ("points_in_boxes", "dali_cli.ppcg.cf", None, "car_points"),
    ("select_models", "dali_cli.ppcg.models", "ModelBank", "select"),
    ("cf_windows", "dali_cli.ppcg.cf", None, "box_windows"),
    ("cf_windows", "dali_cli.ppcg.cf", None, "windows_directions"),
    ("cast_incl_embree", "dali_cli.ppcg.models", "ModelBank", "cast_many"),
    ("embree", "dali_cli.raycast", "Scene", "_trace"),
    ("assemble", "dali_cli.ppcg.rc", None, "assemble"),
    ("assemble", "dali_cli.ppcg.cf", None, "assemble"),
    ("write", "dali_cli.store.artifacts", "FrameSetWriter", "append"),
    ("write", "dali_cli.store.artifacts", "FrameSetWriter", "close"),
)


@contextmanager
def _patched(owner, name: str, wrapper):
    original = getattr(owner, name)
    setattr(owner, name, wrapper(original))
    try:
        yield
    finally:
        setattr(owner, name, original)


class Phases:
    """Sum of wall seconds per phase while active; records Embree calls for `Floor` when asked."""

    def __init__(self, record_traces: bool = False):
        self.seconds: dict[str, float] = {}
        self.cpu_seconds: dict[str, float] = {}  # this thread's CPU time: steadier under load
        self.traces: list[tuple] = []  # (scene, origins, directions, tfar before the call)
        self.rays = 0
        self._record = record_traces
        self._stack = ExitStack()

    def _wrapper(self, phase: str):
        seconds, cpu_seconds, phases = self.seconds, self.cpu_seconds, self

        def wrap(original):
            def timed(*args, **kwargs):
                if phase == "embree":
                    scene, origins, directions, tfar = args
                    phases.rays += len(origins)
                    if phases._record:
                        phases.traces.append(
                            (scene, origins.copy(), directions.copy(), tfar.copy())
                        )
                started, started_cpu = time.perf_counter(), time.thread_time()
                try:
                    return original(*args, **kwargs)
                finally:
                    seconds[phase] = seconds.get(phase, 0.0) + time.perf_counter() - started
                    cpu = time.thread_time() - started_cpu
                    cpu_seconds[phase] = cpu_seconds.get(phase, 0.0) + cpu

            return timed

        return wrap

    def __enter__(self) -> Phases:
        import importlib

        for phase, module_name, owner_name, name in _WRAPPED:
            module = importlib.import_module(module_name)
            owner = getattr(module, owner_name) if owner_name else module
            self._stack.enter_context(_patched(owner, name, self._wrapper(phase)))
        return self

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def per_frame(self, frames: int, loop_seconds: float, cpu: bool = False) -> dict:
        """Seconds per frame of each phase (exclusive: the ray set-up excludes Embree), and
        `other` = the frame loop minus all phases (bookkeeping); `cpu`: CPU seconds of the
        calling thread instead of wall seconds (then loop_seconds is CPU seconds too)."""
        s = dict(self.cpu_seconds if cpu else self.seconds)
        cast = s.pop("cast_incl_embree", 0.0)
        s["ray_setup"] = max(cast - s.get("embree", 0.0), 0.0)
        s["other"] = max(loop_seconds - sum(s.values()), 0.0)
        return {k: round(v / max(frames, 1), 6) for k, v in sorted(s.items())}


def _chunk_files(frames_dir: Path) -> tuple[list[Path], bool]:
    """Chunk files of a frame set's points array, and whether they are zstd-compressed."""
    array = Path(frames_dir) / "frames.zarr" / "points"
    meta = json.loads((array / "zarr.json").read_text())
    codecs = [c["name"] for c in meta["codecs"]]
    files = sorted((array / "c").glob("*/0"), key=lambda p: int(p.parent.name))
    return files, "zstd" in codecs


def floor_read(frames_dir: Path) -> tuple[float, float]:
    """(Wall, CPU) seconds to read, CRC-check and decode every points chunk of a frame set (module doc)."""
    import google_crc32c
    from numcodecs import Zstd

    files, compressed = _chunk_files(frames_dir)
    started, started_cpu = time.perf_counter(), time.process_time()
    for path in files:
        data = np.fromfile(path, dtype=np.uint8)  # one read into one buffer
        body = data[:-4]
        if google_crc32c.value(body) != int.from_bytes(data[-4:].tobytes(), "little"):
            raise ValueError(f"{path}: checksum mismatch")
        np.frombuffer(Zstd().decode(body) if compressed else body, np.float32)
    return time.perf_counter() - started, time.process_time() - started_cpu


def floor_write(points: np.ndarray, chunk_points: int) -> tuple[float, float]:
    """(Wall, CPU) seconds to write `points` `(N, 4)` float32 as raw chunk files with a CRC-32C each (the
    last one padded to a whole chunk, as the format stores it)."""
    from dali_cli.store.raw_chunks import write_chunk

    points = np.ascontiguousarray(points, np.float32)
    with tempfile.TemporaryDirectory(prefix="dali-floor-") as tmp:
        started, started_cpu = time.perf_counter(), time.process_time()
        for number, first in enumerate(range(0, len(points), chunk_points)):
            chunk = points[first : first + chunk_points]
            if len(chunk) < chunk_points:
                chunk = np.concatenate(
                    [chunk, np.zeros((chunk_points - len(chunk), 4), np.float32)]
                )
            write_chunk(Path(tmp) / str(number), chunk)
        return time.perf_counter() - started, time.process_time() - started_cpu


def floor_embree(traces: list[tuple]) -> tuple[float, float]:
    """(Wall, CPU) seconds of the recorded Embree calls replayed bare (fresh tfar each, BVHs cached)."""
    fresh = [(scene, o, d, t.copy()) for scene, o, d, t in traces]
    started, started_cpu = time.perf_counter(), time.process_time()
    for scene, origins, directions, tfar in fresh:
        scene._scene.run(origins, directions, dists=tfar, output=1)
    return time.perf_counter() - started, time.process_time() - started_cpu
