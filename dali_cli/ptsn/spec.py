"""PTSN's vocabulary: the scale range swept, the expected-size specs (E_est), the errors, and the
detector protocol the search runs."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from dali_cli import quantities

SCALE_DECIMALS = 9  # cache keys: scales equal to 1e-9 are the same scale
DEFAULT_STEP = 0.01
DEFAULT_ROS_FACTOR = 0.875  # mean of U(0.75, 1.0), the ROS default of ST3D / dali pretrain


class PTSNError(Exception):
    """A PTSN failure the CLI reports as a ClickException (no detections, bad sizes, ...)."""


class NoDetectionsError(PTSNError):
    """No box with score >= score_min at any tried scale: E_pred, and so ŝ, is undefined."""


# what find_scale does when the detector finds nothing: "identity" returns s = 1 (no size
# normalization) with a warning and fallback "no-detections"; "error" raises NoDetectionsError
NO_DETECTIONS_POLICIES = ("identity", "error")
NO_DETECTIONS_ADVICE = (
    "the model scores no car that high on these frames: train it on more frames or epochs, "
    "lower --score-min, or sweep more frames"
)


class Predictor(Protocol):
    """What PTSN needs from a detector."""

    def predict(
        self, points_list: list[np.ndarray], scale: float = 1.0, mount_height_m: float | None = None
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per frame (boxes (M, 7) float64 de-scaled to the original frame, scores (M,))."""
        ...


# ---------------------------------------------------------------------------------------------
# Scale ranges


@dataclass(frozen=True)
class ScaleRange:
    """Swept scales: `low` .. `high` (inclusive) in steps of `step`; all > 0."""

    low: float
    high: float
    step: float = DEFAULT_STEP

    def grid(self) -> np.ndarray:
        """`(K,)` float64 grid scales, low first; `high` is included even off the step."""
        count = int(math.floor((self.high - self.low) / self.step + 1e-6))
        grid = self.low + self.step * np.arange(count + 1, dtype=np.float64)
        if grid[-1] < self.high - 1e-9:
            grid = np.append(grid, self.high)
        return np.round(grid, SCALE_DECIMALS)

    def as_list(self) -> list[float]:
        return [self.low, self.high, self.step]


def parse_scale_range(text: str) -> ScaleRange:
    """Parse `LOW:HIGH` or `LOW:HIGH:STEP` (default step 0.01); ValueError says what is wrong."""
    parts = str(text).strip().split(":")
    if len(parts) not in (2, 3):
        raise ValueError(f"'{text}' is not LOW:HIGH or LOW:HIGH:STEP")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"'{text}': LOW, HIGH and STEP must be numbers") from None
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"'{text}': values must be finite")
    low, high = values[:2]
    step = values[2] if len(values) == 3 else DEFAULT_STEP
    for value in (low, high):
        problem = quantities.SCALE.problem(value)
        if problem is not None:
            raise ValueError(f"'{text}': {problem}")
    if not low < high:
        raise ValueError(f"'{text}': LOW must be < HIGH")
    if not 0 < step <= high - low:
        raise ValueError(f"'{text}': STEP must satisfy 0 < STEP <= HIGH - LOW, got {step:g}")
    if (high - low) / step > 10_000:
        raise ValueError(f"'{text}': more than 10000 scales; use a larger STEP")
    return ScaleRange(low, high, step)


def parse_size(text: str) -> tuple[float, float, float]:
    """Parse `L,W,H` in metres (all > 0); ValueError otherwise."""
    parts = str(text).split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise ValueError(f"'{text}' is not L,W,H in metres") from None
    if len(values) != 3 or not all(math.isfinite(v) and v > 0 for v in values):
        raise ValueError(f"'{text}' must be three positive numbers L,W,H")
    return values  # type: ignore[return-value]


def ros_expected_size(source_lwh: Sequence[float], ros_factor: float) -> np.ndarray:
    """E_est under random object scaling: the source mean size times the mean ROS factor, (3,)."""
    return np.asarray(source_lwh, dtype=np.float64) * float(ros_factor)
