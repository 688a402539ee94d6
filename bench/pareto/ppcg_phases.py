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
    ("read", "dali_cli.artifacts", "FrameSet", "_read_points"),
    ("read", "dali_cli.artifacts", "FrameSet", "_checked"),
    ("points_in_boxes", "dali_cli.ppcg.rc", None, "car_points"),
    ("points_in_boxes", "dali_cli.ppcg.cf", None, "car_points"),
    ("select_models", "dali_cli.ppcg.models", "ModelBank", "select"),
    ("cf_windows", "dali_cli.ppcg.cf", None, "box_windows"),
    ("cf_windows", "dali_cli.ppcg.cf", None, "window_rays"),
    ("cast_incl_embree", "dali_cli.ppcg.models", "ModelBank", "cast_many"),
    ("embree", "dali_cli.raycast", "Scene", "_trace"),
    ("assemble", "dali_cli.ppcg.rc", None, "assemble"),
    ("assemble", "dali_cli.ppcg.cf", None, "assemble"),
    ("write", "dali_cli.artifacts", "FrameSetWriter", "append"),
    ("write", "dali_cli.artifacts", "FrameSetWriter", "close"),
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
        self.traces: list[tuple] = []  # (scene, origins, directions, tfar before the call)
        self.rays = 0
        self._record = record_traces
        self._stack = ExitStack()

    def _wrapper(self, phase: str):
        seconds, phases = self.seconds, self

        def wrap(original):
            def timed(*args, **kwargs):
                if phase == "embree":
                    scene, origins, directions, tfar = args
                    phases.rays += len(origins)
                    if phases._record:
                        phases.traces.append((scene, origins.copy(), directions.copy(), tfar.copy()))
                started = time.perf_counter()
                try:
                    return original(*args, **kwargs)
                finally:
                    seconds[phase] = seconds.get(phase, 0.0) + time.perf_counter() - started

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

    def per_frame(self, frames: int, loop_seconds: float) -> dict:
        """Seconds per frame of each phase (exclusive: the ray set-up excludes Embree), and
        `other` = the frame loop minus all phases (bookkeeping)."""
        s = dict(self.seconds)
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


def floor_read(frames_dir: Path) -> float:
    """Seconds to read, CRC-check and decode every points chunk of a frame set (module doc)."""
    import google_crc32c
    from numcodecs import Zstd

    files, compressed = _chunk_files(frames_dir)
    started = time.perf_counter()
    for path in files:
        data = path.read_bytes()
        body = data[:-4]
        if google_crc32c.value(body) != int.from_bytes(data[-4:], "little"):
            raise ValueError(f"{path}: checksum mismatch")
        raw = Zstd().decode(body) if compressed else body
        np.frombuffer(raw, np.float32)
    return time.perf_counter() - started


def floor_write(points: np.ndarray, chunk_points: int) -> float:
    """Seconds to write `points` `(N, 4)` float32 as raw chunk files with a CRC-32C each."""
    import google_crc32c

    points = np.ascontiguousarray(points, np.float32)
    with tempfile.TemporaryDirectory(prefix="dali-floor-") as tmp:
        started = time.perf_counter()
        for number, first in enumerate(range(0, len(points), chunk_points)):
            body = points[first : first + chunk_points].tobytes()
            with open(Path(tmp) / str(number), "wb") as handle:
                handle.write(body)
                handle.write(google_crc32c.value(body).to_bytes(4, "little"))
        return time.perf_counter() - started


def floor_embree(traces: list[tuple]) -> float:
    """Seconds of the recorded Embree calls replayed bare (fresh tfar each, BVHs cached)."""
    fresh = [(scene, o, d, t.copy()) for scene, o, d, t in traces]
    started = time.perf_counter()
    for scene, origins, directions, tfar in fresh:
        scene._scene.run(origins, directions, dists=tfar, output=1)
    return time.perf_counter() - started
