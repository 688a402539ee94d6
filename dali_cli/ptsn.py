"""Post-training size normalization (PTSN): find the point-cloud scale ŝ at which a trained
detector's mean predicted car size E_pred(s) matches the expected target size E_est, label-free.

E_pred(s) (paper Eq. 1): run the detector on s·P (scaled about the ground), de-scale the boxes
(centers and sizes / s, yaw kept), keep score >= score_min, take the per-frame mean (l, w, h) and
average it over the frames that have detections (`mean="pooled"`: one mean over all boxes).
Both criteria are written as a 1-D function c(s) that decreases with s and is zero at ŝ:

- volume: c(s) = log(l·w·h of E_pred(s)) - log(l·w·h of E_est).
- lwh:    c(s) = Σ_d E_pred_d (E_pred_d - E_est_d) / Σ_d E_est_d², the stationarity condition of
          the least squares Σ_d (E_pred_d(s) - E_est_d)² when each size falls like 1/s near ŝ
          (the de-scaling law), so its root is the least-squares scale.

The detector is anything with `predict(points_list, scale=..., mount_height_m=...)` (Predictor);
detections are cached per (frame, scale) so that no detector pass ever repeats.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

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
    if low <= 0:
        raise ValueError(f"'{text}': LOW must be > 0 (a scale), got {low:g}")
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


# ---------------------------------------------------------------------------------------------
# E_pred


@dataclass(frozen=True)
class SizeStats:
    """E_pred over a set of frames at one scale."""

    frames: int  # frames evaluated
    frames_with_boxes: int
    boxes: int
    mean_lwh: np.ndarray  # (3,) float64, NaN when no boxes

    @property
    def volume(self) -> float:
        """l·w·h of the mean size (NaN without boxes)."""
        return float(np.prod(self.mean_lwh))


def expected_prediction(
    sizes_per_frame: Sequence[np.ndarray], mean: str = "per-frame"
) -> SizeStats:
    """E_pred from de-scaled box sizes `[(M_i, 3)]` (l, w, h) of the frames, already score-filtered.

    per-frame: mean over frames with boxes of each frame's mean size (paper Eq. 1); pooled: one
    mean over all boxes (the reference code).
    """
    counts = np.array([len(s) for s in sizes_per_frame], dtype=np.int64)  # (F,)
    total = int(counts.sum())
    with_boxes = int(np.count_nonzero(counts))
    if total == 0:
        return SizeStats(len(counts), 0, 0, np.full(3, np.nan))
    stacked = np.concatenate([np.asarray(s, np.float64).reshape(-1, 3) for s in sizes_per_frame])
    if mean == "pooled":
        mean_lwh = stacked.mean(axis=0)
    elif mean == "per-frame":
        frame_of_box = np.repeat(np.arange(len(counts)), counts)  # (B,)
        sums = np.zeros((len(counts), 3))
        np.add.at(sums, frame_of_box, stacked)
        present = counts > 0
        mean_lwh = (sums[present] / counts[present, None]).mean(axis=0)
    else:
        raise ValueError(f"mean must be 'per-frame' or 'pooled', got {mean!r}")
    return SizeStats(len(counts), with_boxes, total, mean_lwh)


def criterion(mean_lwh: np.ndarray, e_est: np.ndarray, match: str = "volume") -> float:
    """c(s) of the module docstring for E_pred = `mean_lwh` (3,): decreasing in s, 0 at ŝ; NaN
    when E_pred is undefined (no boxes)."""
    mean_lwh = np.asarray(mean_lwh, np.float64)
    e_est = np.asarray(e_est, np.float64)
    if not np.isfinite(mean_lwh).all():
        return float("nan")
    if match == "volume":
        return float(np.sum(np.log(np.maximum(mean_lwh, 1e-12))) - np.sum(np.log(e_est)))
    if match == "lwh":
        return float(np.dot(mean_lwh, mean_lwh - e_est) / np.dot(e_est, e_est))
    raise ValueError(f"match must be 'volume' or 'lwh', got {match!r}")


# ---------------------------------------------------------------------------------------------
# Detection cache


class DetectionCache:
    """Detections per (frame index, scale), computed at most once.

    frames: indexable `frames[i] -> (n, 4) float32` (a list, or a lazy FrameSet reader).
    Keeps only boxes with score >= score_min. `frame_passes` counts detector runs on one frame.
    """

    def __init__(
        self,
        detector: Predictor,
        frames,
        score_min: float = 0.3,
        mount_height_m: float | None = None,
        batch_size: int = 8,
        progress: Callable[[int], None] | None = None,
    ):
        self.detector = detector
        self.frames = frames
        self.score_min = float(score_min)
        self.mount_height_m = mount_height_m
        self.batch_size = max(1, int(batch_size))
        self.progress = progress
        self._store: dict[tuple[int, float], tuple[np.ndarray, np.ndarray]] = {}
        self.frame_passes = 0
        self.seconds = 0.0

    @staticmethod
    def key(scale: float) -> float:
        return round(float(scale), SCALE_DECIMALS)

    def detections(
        self, scale: float, indices: Sequence[int]
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """(boxes (M, 7), scores (M,)) per frame of `indices` at `scale`; missing ones are run."""
        scale = self.key(scale)
        missing = [int(i) for i in indices if (int(i), scale) not in self._store]
        started = time.perf_counter()
        for start in range(0, len(missing), self.batch_size):
            batch = missing[start : start + self.batch_size]
            points = [self.frames[i] for i in batch]
            results = self.detector.predict(points, scale=scale, mount_height_m=self.mount_height_m)
            if len(results) != len(batch):
                raise PTSNError(f"detector returned {len(results)} results for {len(batch)} frames")
            for index, (boxes, scores) in zip(batch, results, strict=True):
                boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
                scores = np.asarray(scores, np.float32).reshape(-1)
                keep = scores >= self.score_min
                self._store[(index, scale)] = (boxes[keep], scores[keep])
            self.frame_passes += len(batch)
            if self.progress is not None:
                self.progress(len(batch))
        self.seconds += time.perf_counter() - started
        return [self._store[(int(i), scale)] for i in indices]

    def sizes(self, scale: float, indices: Sequence[int]) -> list[np.ndarray]:
        """De-scaled sizes `(M, 3)` per frame."""
        return [boxes[:, 3:6] for boxes, _ in self.detections(scale, indices)]

    @property
    def scales(self) -> list[float]:
        return sorted({scale for _, scale in self._store})


# ---------------------------------------------------------------------------------------------
# Search


@dataclass
class Evaluation:
    """One evaluated (scale, frame set): a row of sweep.parquet."""

    scale: float
    subset: str  # "subsample" or "all"
    phase: str  # "bracket", "confirm", "grid", "local-grid"
    stats: SizeStats
    value: float  # criterion c(s), NaN without boxes
    seconds: float
    frame_passes: int  # new detector frame passes this evaluation cost

    def row(self) -> dict:
        lwh = self.stats.mean_lwh
        return {
            "scale": self.scale,
            "subset": self.subset,
            "phase": self.phase,
            "frames": self.stats.frames,
            "frames_with_boxes": self.stats.frames_with_boxes,
            "boxes": self.stats.boxes,
            "mean_l": float(lwh[0]),
            "mean_w": float(lwh[1]),
            "mean_h": float(lwh[2]),
            "mean_volume": self.stats.volume,
            "criterion": self.value,
            "seconds": self.seconds,
            "frame_passes": self.frame_passes,
        }


@dataclass
class SearchResult:
    """ŝ and how it was found."""

    scale: float
    mean_lwh: np.ndarray  # (3,) E_pred at ŝ (interpolated between evaluated scales)
    strategy: str
    clipped: str | None  # None, "low" or "high": E_est lies outside the swept range
    # None, "local-grid" (curve not monotone within noise) or "no-detections" (s = 1, see
    # NO_DETECTIONS_POLICIES)
    fallback: str | None
    monotone: bool | None  # None when no curve was found (fallback "no-detections")
    evaluations: list[Evaluation] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


class _Evaluator:
    """Evaluates c(s) on a frame subset through the cache and records every evaluation."""

    def __init__(self, cache: DetectionCache, e_est, match: str, mean: str):
        self.cache = cache
        self.e_est = np.asarray(e_est, np.float64)
        self.match = match
        self.mean = mean
        self.evaluations: list[Evaluation] = []
        self._done: dict[tuple[float, str], Evaluation] = {}

    def __call__(self, scale: float, indices: Sequence[int], subset: str, phase: str) -> Evaluation:
        scale = DetectionCache.key(scale)
        if (scale, subset) in self._done:
            return self._done[(scale, subset)]
        passes_before, seconds_before = self.cache.frame_passes, self.cache.seconds
        stats = expected_prediction(self.cache.sizes(scale, indices), self.mean)
        evaluation = Evaluation(
            scale=scale,
            subset=subset,
            phase=phase,
            stats=stats,
            value=criterion(stats.mean_lwh, self.e_est, self.match),
            seconds=self.cache.seconds - seconds_before,
            frame_passes=self.cache.frame_passes - passes_before,
        )
        self._done[(scale, subset)] = evaluation
        self.evaluations.append(evaluation)
        return evaluation

    def curve(self, subset: str) -> tuple[np.ndarray, np.ndarray]:
        """Evaluated (scales (K,), values (K,)) of `subset` with defined values, by scale."""
        found = sorted(
            (e.scale, e.value)
            for e in self.evaluations
            if e.subset == subset and math.isfinite(e.value)
        )
        if not found:
            return np.zeros(0), np.zeros(0)
        scales, values = np.array(found).T
        return scales, values

    def lwh_at(self, subset: str, scale: float) -> np.ndarray:
        """E_pred (3,) at `scale`, linear between the nearest evaluated scales of `subset`."""
        found = sorted(
            (e.scale, e.stats.mean_lwh)
            for e in self.evaluations
            if e.subset == subset and np.isfinite(e.stats.mean_lwh).all()
        )
        if not found:
            return np.full(3, np.nan)
        scales = np.array([s for s, _ in found])
        lwh = np.stack([m for _, m in found])  # (K, 3)
        return np.array([np.interp(scale, scales, lwh[:, d]) for d in range(3)])


def decreasing_fit(values: np.ndarray) -> np.ndarray:
    """Least-squares non-increasing fit of `values` (K,) (pool adjacent violators), (K,)."""
    blocks: list[list[float]] = []  # [mean, weight]; loops over scales (few), not points
    for value in np.asarray(values, np.float64):
        blocks.append([value, 1.0])
        while len(blocks) > 1 and blocks[-2][0] < blocks[-1][0]:
            value_b, weight_b = blocks.pop()
            value_a, weight_a = blocks.pop()
            weight = weight_a + weight_b
            blocks.append([(value_a * weight_a + value_b * weight_b) / weight, weight])
    return np.concatenate([np.full(int(w), v) for v, w in blocks])


def is_monotone(scales: np.ndarray, values: np.ndarray, noise: float) -> bool:
    """True when `values` (K,) never rise by more than `noise` as `scales` (K,) grow."""
    order = np.argsort(scales)
    values = np.asarray(values)[order]
    if len(values) < 2:
        return True
    running_min = np.minimum.accumulate(values)
    return bool(np.all(values - running_min <= noise))


def crossing(scales: np.ndarray, values: np.ndarray) -> tuple[float, str | None]:
    """Scale where a non-increasing curve (K,) crosses 0, linear between points.

    Returns (scale, clipped) with clipped "low" when the curve is already <= 0 at the first scale
    (E_est needs a smaller scale), "high" when it is still > 0 at the last.
    """
    if values[0] <= 0:
        return float(scales[0]), ("low" if values[0] < 0 else None)
    if values[-1] > 0:
        return float(scales[-1]), "high"
    upper = int(np.flatnonzero(values <= 0)[0])  # first point at/below zero, >= 1
    s0, s1, v0, v1 = scales[upper - 1], scales[upper], values[upper - 1], values[upper]
    if v1 == 0 or v0 == v1:
        return float(s1), None
    return float(s0 + (s1 - s0) * v0 / (v0 - v1)), None


def _defined_end(evaluate, grid: np.ndarray, from_low: bool) -> Evaluation | None:
    """First grid scale from one end where the detector finds boxes: tries 0, 1, 3, 7, ... steps in."""
    offset = 0
    while offset < len(grid):
        scale = grid[offset] if from_low else grid[len(grid) - 1 - offset]
        evaluation = evaluate(scale)
        if math.isfinite(evaluation.value):
            return evaluation
        offset = 2 * offset + 1
    return None


def grid_search(evaluator: _Evaluator, grid: np.ndarray, indices, noise: float, phase="grid"):
    """Evaluate every grid scale on `indices`; ŝ from a non-increasing fit (robust to noise)."""
    for scale in grid:
        evaluator(scale, indices, "all", phase)
    scales, values = evaluator.curve("all")
    inside = (scales >= grid[0] - 1e-12) & (scales <= grid[-1] + 1e-12)
    scales, values = scales[inside], values[inside]
    if len(scales) == 0:
        raise NoDetectionsError(
            f"no detections with score >= {evaluator.cache.score_min} at any scale "
            f"{grid[0]:g}..{grid[-1]:g}: cannot estimate E_pred"
        )
    monotone = is_monotone(scales, values, noise)
    scale, clipped = crossing(scales, decreasing_fit(values))
    return scale, clipped, monotone


def bracket_search(
    evaluator: _Evaluator,
    grid: np.ndarray,
    subsample: np.ndarray,
    all_frames: np.ndarray,
    noise: float,
    max_iterations: int = 12,
    local_steps: int = 5,
) -> tuple[float, str | None, str | None, bool, list[str]]:
    """Bracket/secant on `subsample`, then confirm on `all_frames` at the grid scales around it.

    Phase 1 (subsample): evaluate the range ends, then Illinois regula falsi on c(s) until the
    bracket is one grid step wide. Phase 2 (all frames): evaluate the two grid scales around the
    phase-1 root, walking outwards until c changes sign between them, and interpolate. When the
    evaluated curve rises by more than `noise` anywhere, fall back to a local grid (± local_steps)
    on all frames with a non-increasing fit. Returns (ŝ, clipped, fallback, monotone, warnings).
    """
    warnings: list[str] = []
    step = float(grid[1] - grid[0]) if len(grid) > 1 else 1.0

    def on_subsample(scale: float) -> Evaluation:
        return evaluator(scale, subsample, "subsample", "bracket")

    def on_all(scale: float, phase: str = "confirm") -> Evaluation:
        return evaluator(scale, all_frames, "all", phase)

    low = _defined_end(on_subsample, grid, from_low=True)
    high = _defined_end(on_subsample, grid, from_low=False)
    if low is None or high is None:
        raise NoDetectionsError(
            f"no detections with score >= {evaluator.cache.score_min} at any tried scale in "
            f"{grid[0]:g}..{grid[-1]:g} on {len(subsample)} frames: cannot estimate E_pred"
        )
    # phase 1: c decreases with s; keep c(low) > 0 >= c(high)
    estimate = None
    if low.value <= 0:
        estimate = low.scale
    elif high.value > 0:
        estimate = high.scale
    else:
        lo_s, lo_v, hi_s, hi_v = low.scale, low.value, high.scale, high.value
        side = 0  # Illinois: halve the weight of an end that stays twice in a row
        for _ in range(max_iterations):
            if hi_s - lo_s <= step:
                break
            guess = hi_s - hi_v * (hi_s - lo_s) / (hi_v - lo_v)
            margin = 0.05 * (hi_s - lo_s)  # keep strictly inside so the bracket always shrinks
            guess = float(np.clip(guess, lo_s + margin, hi_s - margin))
            value = on_subsample(guess).value
            if not math.isfinite(value):
                guess = 0.5 * (lo_s + hi_s)
                value = on_subsample(guess).value
                if not math.isfinite(value):
                    break
            if value > 0:
                lo_s, lo_v = guess, value
                if side == -1:
                    hi_v *= 0.5
                side = -1
            else:
                hi_s, hi_v = guess, value
                if side == 1:
                    lo_v *= 0.5
                side = 1
        estimate = lo_s + (hi_s - lo_s) * lo_v / (lo_v - hi_v) if lo_v != hi_v else lo_s
    sub_scales, sub_values = evaluator.curve("subsample")
    monotone = is_monotone(sub_scales, sub_values, noise)

    # phase 2: confirm on all frames at the grid scales around the estimate
    clipped = None
    if monotone:
        below = int(np.clip(np.searchsorted(grid, estimate + 1e-12) - 1, 0, len(grid) - 1))
        above = min(below + 1, len(grid) - 1)
        for _ in range(len(grid)):
            a, b = on_all(grid[below]), on_all(grid[above])
            if not (math.isfinite(a.value) and math.isfinite(b.value)):
                break
            if a.value <= 0 and below > 0:
                below, above = below - 1, below
            elif b.value > 0 and above < len(grid) - 1:
                below, above = above, above + 1
            else:
                break
        scales, values = evaluator.curve("all")
        monotone = is_monotone(scales, values, noise)
        if monotone and len(scales):
            scale, clipped = crossing(scales, decreasing_fit(values))
            return scale, clipped, None, True, warnings

    # fallback: a local grid on all frames around the estimate
    warnings.append(
        f"E_pred is not monotone in the scale within noise {noise:g}: fell back to a local grid "
        f"of +-{local_steps} steps around s = {estimate:.3f}"
    )
    centre = int(np.argmin(np.abs(grid - estimate)))
    window = grid[max(0, centre - local_steps) : centre + local_steps + 1]
    for scale in window:
        on_all(scale, "local-grid")
    scales, values = evaluator.curve("all")
    if len(scales) == 0:
        raise PTSNError("no detections on the selected frames near the estimated scale")
    fitted = decreasing_fit(values)
    scale, clipped = crossing(scales, fitted)
    at_window_edge = clipped is not None and (
        (clipped == "low" and window[0] > grid[0]) or (clipped == "high" and window[-1] < grid[-1])
    )
    if at_window_edge:  # the crossing left the local window: the full grid decides
        warnings.append("the crossing is outside the local grid: evaluated the full grid")
        scale, clipped, _ = grid_search(evaluator, grid, all_frames, noise, phase="local-grid")
    return scale, clipped, "local-grid", False, warnings


def find_scale(
    cache: DetectionCache,
    scale_range: ScaleRange,
    e_est,
    frames: Sequence[int],
    *,
    search: str = "bracket",
    match: str = "volume",
    mean: str = "per-frame",
    subsample: Sequence[int] | None = None,
    noise: float = 0.02,
    no_detections: str = "error",
) -> SearchResult:
    """ŝ where E_pred(s) matches `e_est` (3,) over the frame indices `frames`.

    search: "bracket" (subsample first, then confirm on all frames) or "grid" (every scale of
    `scale_range` on all frames). noise: how much c(s) may rise with s and still count as
    monotone (volume: a log ratio, 0.02 = 2 %). no_detections: what happens when no box reaches
    the cache's score_min at any tried scale, "error" (NoDetectionsError) or "identity" (ŝ = 1,
    fallback "no-detections", E_pred NaN, a warning that says what to do).
    """
    if no_detections not in NO_DETECTIONS_POLICIES:
        raise ValueError(f"no_detections must be one of {NO_DETECTIONS_POLICIES}")
    e_est = np.asarray(e_est, np.float64)
    if e_est.shape != (3,) or not (np.isfinite(e_est).all() and (e_est > 0).all()):
        raise PTSNError(f"expected size must be three positive numbers, got {e_est}")
    frames = np.asarray(frames, dtype=np.int64)
    if len(frames) == 0:
        raise PTSNError("no frames with points in range to evaluate")
    evaluator = _Evaluator(cache, e_est, match, mean)
    try:
        return _search(evaluator, scale_range.grid(), frames, search, subsample, noise)
    except NoDetectionsError as error:
        if no_detections == "error":
            raise NoDetectionsError(f"{error} ({NO_DETECTIONS_ADVICE})") from None
        warning = (
            f"{error}: ŝ = 1 (no size normalization) instead; {NO_DETECTIONS_ADVICE} "
            "(--no-detections error stops here instead)"
        )
        return SearchResult(
            scale=1.0,
            mean_lwh=np.full(3, np.nan),
            strategy=search,
            clipped=None,
            fallback="no-detections",
            monotone=None,
            evaluations=evaluator.evaluations,
            warnings=[warning],
        )


def _search(evaluator: _Evaluator, grid: np.ndarray, frames, search, subsample, noise):
    """find_scale's search proper (NoDetectionsError when no scale gives boxes)."""
    warnings: list[str] = []
    if search == "grid":
        scale, clipped, monotone = grid_search(evaluator, grid, frames, noise)
        fallback = None
        if not monotone:
            warnings.append(
                f"E_pred is not monotone in the scale within noise {noise:g}: ŝ comes from a "
                "non-increasing fit of the grid"
            )
    elif search == "bracket":
        subsample = frames if subsample is None else np.asarray(subsample, np.int64)
        scale, clipped, fallback, monotone, found = bracket_search(
            evaluator, grid, subsample, frames, noise
        )
        warnings.extend(found)
    else:
        raise ValueError(f"search must be 'bracket' or 'grid', got {search!r}")
    if clipped is not None:
        bound = "lower" if clipped == "low" else "upper"
        warnings.append(
            f"E_est lies outside the swept range: ŝ clipped to the {bound} bound {scale:g} "
            f"(widen --scales)"
        )
    return SearchResult(
        scale=float(scale),
        mean_lwh=evaluator.lwh_at("all", scale),
        strategy=search,
        clipped=clipped,
        fallback=fallback,
        monotone=monotone,
        evaluations=evaluator.evaluations,
        warnings=warnings,
    )


# ---------------------------------------------------------------------------------------------
# Frames and subsamples


def select_frames(count: int, frames: int | None, fraction: float | None, seed: int) -> np.ndarray:
    """Sorted indices `(k,)` of a seeded subsample of `count` frames (all when both are None)."""
    if frames is not None and fraction is not None:
        raise ValueError("give either a frame count or a frame fraction, not both")
    if fraction is not None:
        frames = max(1, int(round(fraction * count)))
    if frames is None or frames >= count:
        return np.arange(count, dtype=np.int64)
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(count, size=frames, replace=False)).astype(np.int64)


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


# ---------------------------------------------------------------------------------------------
# Plot


def plot_sweep(rows: Sequence[dict], scale: float, e_est, path, title: str = "") -> None:
    """Mean predicted volume vs scale with the E_est volume line and ŝ marked (paper Fig. 3)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    for subset, marker, colour in (("all", "o-", "tab:blue"), ("subsample", "x", "tab:gray")):
        points = sorted(
            (r["scale"], r["mean_volume"])
            for r in rows
            if r["subset"] == subset and math.isfinite(r["mean_volume"])
        )
        if points:
            xs, ys = zip(*points, strict=True)
            label = "E_pred, all frames" if subset == "all" else "E_pred, subsample"
            axis.plot(xs, ys, marker, color=colour, markersize=4, label=label)
    target_volume = float(np.prod(e_est))
    axis.axhline(
        target_volume, color="tab:red", linestyle="--", label=f"E_est {target_volume:.2f} m³"
    )
    axis.axvline(scale, color="tab:green", linestyle=":", label=f"ŝ = {scale:.3f}")
    axis.set_xlabel("scale s")
    axis.set_ylabel("mean predicted volume (m³)")
    axis.set_title(title or "PTSN sweep")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)
