"""Ground fit of pseudo boxes (`dali pseudo-label --fit-ground`): put each box's bottom on the
ground the target points show around it, its x, y, size and yaw kept. Target points only, no label.

Why: a car stands on the road, and the road's points around a box tell its height better than the
detector's z does far out, where a car holds a few dozen points. On seed 0's iteration-1 labels
(docs/RESULTS.md, session 29) the matched boxes' bottoms are off the true ones by a standard
deviation of 0.035 / 0.060 / 0.113 m at 0-30 / 30-50 / 50-80 m.

For each box the ground candidates are the points within `ring_m` of its footprint (in the box's
frame), within ±`window_m` of its bottom, and in no box of the frame grown by `CLAIM_MARGIN_M`
(cars, their own and their neighbours'). The ground height is a robust fit over them: start from
the points at most 0.05 m above their median height, then a few rounds of least squares, each
keeping the candidates within `inlier_m` of the fit. The fit is a plane z = a + b u + c v in the
box's frame (u along, v across; `a` is the height under the box's centre) when the inliers span
more than `plane_span_m` both ways and number more than `plane_points` (far out the ground rings
are metres apart: a slope from one ring is a guess), else a constant. A box keeps its z when fewer
than `min_points` inliers remain or the ground lies more than `max_shift_m` from its bottom.

Lengths in metres; boxes (x, y, z, l, w, h, yaw) with z the centre, in the sensor frame.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from dali_cli.ppcg.inbox import points_per_box

CLAIM_MARGIN_M = 0.3  # a point this close to a box is its car's, not the road's
START_ABOVE_MEDIAN_M = 0.05  # the first fit uses the candidates at most this above their median
ROUNDS = 4


@dataclass(frozen=True)
class GroundFit:
    """The ground fit's settings (module docstring)."""

    ring_m: float = 10.0
    window_m: float = 0.8
    inlier_m: float = 0.12
    min_points: int = 8
    max_shift_m: float = 0.4
    plane_span_m: float = 3.0
    plane_points: int = 30

    def __post_init__(self):
        for name in ("ring_m", "window_m", "inlier_m", "max_shift_m", "plane_span_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"GroundFit.{name} must be > 0, got {getattr(self, name)}")
        if self.min_points < 3:
            raise ValueError(f"GroundFit.min_points must be >= 3, got {self.min_points}")

    def record(self) -> dict:
        """The settings as the manifest records them."""
        return asdict(self)


def ground_height(u: np.ndarray, v: np.ndarray, z: np.ndarray, fit: GroundFit) -> float:
    """The ground's height at u = v = 0 from candidates `(m,)` each (box frame, m); NaN when
    fewer than fit.min_points inliers remain."""
    if len(z) < fit.min_points:
        return np.nan
    inliers = z <= np.median(z) + START_ABOVE_MEDIAN_M
    for _ in range(ROUNDS):
        if inliers.sum() < fit.min_points:
            return np.nan
        plane = (
            inliers.sum() > fit.plane_points
            and np.ptp(u[inliers]) > fit.plane_span_m
            and np.ptp(v[inliers]) > fit.plane_span_m
        )
        design = np.stack([np.ones_like(u), u, v], axis=1) if plane else np.ones((len(u), 1))
        coef, *_ = np.linalg.lstsq(design[inliers], z[inliers], rcond=None)
        inliers = np.abs(z - design @ coef) < fit.inlier_m
    return float(coef[0]) if inliers.sum() >= fit.min_points else np.nan


def ground_under(boxes: np.ndarray, points: np.ndarray, fit: GroundFit) -> np.ndarray:
    """The ground's height `(K,)` float64 under each box's centre (NaN where not found) from one
    frame's points `(n, >=3)`; boxes `(K, 7)`."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    heights = np.full(len(boxes), np.nan)
    if len(boxes) == 0:
        return heights
    claimed = np.zeros(len(points), bool)
    for members in points_per_box(points, boxes, CLAIM_MARGIN_M):
        claimed[members] = True
    free = np.flatnonzero(~claimed)
    xyz = points[free, :3].astype(np.float64)
    for k, (x, y, z, length, width, height, yaw) in enumerate(boxes):
        cos, sin = np.cos(yaw), np.sin(yaw)
        dx, dy = xyz[:, 0] - x, xyz[:, 1] - y
        u, v = cos * dx + sin * dy, -sin * dx + cos * dy
        bottom = z - height / 2
        near = (np.abs(u) < length / 2 + fit.ring_m) & (np.abs(v) < width / 2 + fit.ring_m)
        near &= np.abs(xyz[:, 2] - bottom) < fit.window_m
        heights[k] = ground_height(u[near], v[near], xyz[near, 2], fit)
    return heights


def fit_heights(
    boxes: np.ndarray, points: np.ndarray, fit: GroundFit
) -> tuple[np.ndarray, np.ndarray]:
    """Boxes `(K, 7)` with each bottom on the ground under it (z = ground + h / 2) where found
    within fit.max_shift_m, and which moved `(K,)` bool."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    ground = ground_under(boxes, points, fit)
    shift = ground - (boxes[:, 2] - boxes[:, 5] / 2)
    moved = np.isfinite(shift) & (np.abs(shift) <= fit.max_shift_m)
    out = boxes.copy()
    out[moved, 2] += shift[moved]
    return out, moved
