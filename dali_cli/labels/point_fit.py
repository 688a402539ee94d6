"""The parameters of the point fit of pseudo boxes (dali_cli.labels.box_fit): its pose grid (shifts
along and across the box, turns) and its cost's caps and weights. Lengths in metres, angles in
degrees (the grid's turns in radians)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import lru_cache

import numpy as np


@dataclass(frozen=True)
class PointFit:
    """The grid and cost of the fit (dali_cli.labels.box_fit's docstring); `max_points`: a box
    with more candidate points is scored on an evenly strided subset of that many (bounded work
    per box: grid x points)."""

    along_m: float = 1.0
    across_m: float = 0.2
    turn_deg: float = 8.0
    along_step_m: float = 0.05
    across_step_m: float = 0.025
    turn_step_deg: float = 1.0
    margin_m: float = 0.6
    ground_clearance_m: float = 0.2
    min_points: int = 10
    side_cap_m: float = 0.5
    outside_weight: float = 30.0
    max_points: int = 512

    def __post_init__(self):
        for name in ("along_m", "across_m", "turn_deg", "margin_m", "ground_clearance_m"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("along_step_m", "across_step_m", "turn_step_deg", "side_cap_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.min_points < 1 or self.max_points < self.min_points:
            raise ValueError("need 1 <= min_points <= max_points")

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """The grid's shifts `(D, 2)` (along m, across m; across varies fastest) and turns `(T,)`
        rad, each axis symmetric about and holding 0 (made once per PointFit: read only)."""
        return grid_axes(self)

    def grid(self) -> np.ndarray:
        """Candidate (along m, across m, turn rad) offsets `(G = D * T, 3)`, the zero offset
        included; pose g is shift g // T turned by turn g % T (the order of pose_costs)."""
        shifts, turns = self.axes()
        return np.concatenate(
            [np.repeat(shifts, len(turns), 0), np.tile(turns, len(shifts))[:, None]], 1
        )

    def record(self) -> dict:
        """The manifest's record of the fit (its every parameter)."""
        return asdict(self)


@lru_cache(maxsize=8)
def grid_axes(fit: PointFit) -> tuple[np.ndarray, np.ndarray]:
    """PointFit.axes, made once per fit: shifts `(D, 2)` m, turns `(T,)` rad."""

    def axis(half: float, step: float) -> np.ndarray:
        count = int(np.floor(half / step + 1e-9))
        return np.arange(-count, count + 1) * step

    along = axis(fit.along_m, fit.along_step_m)
    across = axis(fit.across_m, fit.across_step_m)
    shifts = np.stack(np.meshgrid(along, across, indexing="ij"), -1).reshape(-1, 2)
    for array in (shifts, turns := np.radians(axis(fit.turn_deg, fit.turn_step_deg))):
        array.flags.writeable = False
    return shifts, turns
