"""Which frames PTSN runs on: the seeded selection, the bracket's subsample, and the crop to
what the detector can see at some swept scale."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

FRAME_CAP = 64  # frames a sweep runs on when neither a count nor a fraction is given


def select_frames(count: int, frames: int | None, fraction: float | None, seed: int) -> np.ndarray:
    """Sorted indices `(k,)` of a seeded, evenly spread sample of `count` frames: the frames cut
    into k runs of (nearly) equal length in their order, one frame drawn from each run, so a
    drive's every stretch is represented. k is `frames`, else `fraction` of the frames, else
    FRAME_CAP (every frame when k >= count). docs/ptsn.md has the error of ŝ this costs."""
    if frames is not None and fraction is not None:
        raise ValueError("give either a frame count or a frame fraction, not both")
    if fraction is not None:
        frames = max(1, int(round(fraction * count)))
    frames = FRAME_CAP if frames is None else frames
    if frames >= count:
        return np.arange(count, dtype=np.int64)
    starts = np.arange(frames + 1, dtype=np.int64) * count // frames  # (k + 1,) run edges
    offsets = np.random.default_rng(seed).integers(0, np.diff(starts))  # each run >= 1 frame
    return (starts[:-1] + offsets).astype(np.int64)


def subsample_for_bracket(
    indices: np.ndarray, fraction: float, minimum: int, seed: int
) -> np.ndarray:
    """The phase-1 subsample: `fraction` of `indices` (at least `minimum`), seeded, sorted."""
    size = min(len(indices), max(int(minimum), int(math.ceil(fraction * len(indices)))))
    if size >= len(indices):
        return np.asarray(indices, np.int64)
    rng = np.random.default_rng(seed + 1)
    return np.sort(rng.choice(np.asarray(indices), size=size, replace=False)).astype(np.int64)


def crop_for_scales(
    points: np.ndarray,
    visible_range: Callable[[float], Sequence[float]] | None,
    low: float,
    high: float,
) -> np.ndarray:
    """Drop points `(n, C)` that no scale in [low, high] brings into the detector's view.

    `visible_range(s)` is the detector's (x0, y0, x1, y1) at scale s in the original frame
    (`Detector.visible_range`); its bounds are monotone in s, so the points some swept scale can
    see lie in the hull of the ranges at `low` and `high`. None keeps every point.
    """
    if visible_range is None:
        return points
    ends = np.asarray([visible_range(low), visible_range(high)], np.float64)  # (2, 4)
    lower = ends[:, :2].min(axis=0)  # (2,) x, y
    upper = ends[:, 2:4].max(axis=0)
    xy = points[:, :2]
    return points[np.all((xy >= lower) & (xy <= upper), axis=1)]
