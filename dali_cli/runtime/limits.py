"""Size limits that protect memory: checked where a count or a file size enters, before anything
is allocated, so a typo (`--frames 1000000000000`, `beams = 100000000`, a 2 GB sparse point file)
is a one-line error instead of a machine swapping for minutes and a MemoryError traceback.

Each limit is far above any real dataset and can be raised with its environment variable.
"""

from __future__ import annotations

import os

from dali_cli.runtime.errors import StageError

# name -> (default, environment variable, what is counted)
LIMITS: dict[str, tuple[int, str, str]] = {
    "frames": (10_000_000, "DALI_MAX_FRAMES", "frames in one frame set"),
    "rays_per_frame": (
        50_000_000,
        "DALI_MAX_RAYS_PER_FRAME",
        "rays of one LiDAR frame (beams x points_per_beam)",
    ),
    "point_file_bytes": (
        1 << 30,
        "DALI_MAX_POINT_FILE_BYTES",
        "bytes of one point file (a 128-beam scan is about 30 MB)",
    ),
    "frame_cache_bytes": (
        256 << 20,
        "DALI_FRAME_CACHE_BYTES",
        "bytes of prepared training frames each reading process keeps (0: none)",
    ),
}


class LimitError(StageError):
    """A count or size beyond a limit of LIMITS; the message says how to raise it."""


def limit(name: str) -> int:
    """The limit `name` of LIMITS: its environment variable when set to an integer, else the
    default."""
    default, variable, _ = LIMITS[name]
    text = os.environ.get(variable, "").strip()
    try:
        return int(text) if text else default
    except ValueError:
        raise LimitError(f"{variable}={text!r}: expected an integer") from None


def check_limit(name: str, value: int, where: str) -> None:
    """Raise LimitError naming `where` (an option, a file and field) when `value` exceeds the
    limit `name`."""
    maximum = limit(name)
    if value > maximum:
        _, variable, what = LIMITS[name]
        raise LimitError(
            f"{where}: {value} exceeds the limit of {maximum} {what}; if this is intended and "
            f"the machine can hold it, set {variable} to a larger value"
        )
