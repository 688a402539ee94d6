"""The search for ŝ: grid and bracket (secant on a subsample, confirmed on all frames), the
monotonicity check and the crossing."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from dali_cli.ptsn.cache import DetectionCache
from dali_cli.ptsn.spec import (
    NO_DETECTIONS_ADVICE,
    NO_DETECTIONS_POLICIES,
    NoDetectionsError,
    PTSNError,
    ScaleRange,
)
from dali_cli.ptsn.stats import SizeStats, criterion, expected_prediction


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


def _illinois(on_subsample, low: Evaluation, high: Evaluation, step: float, max_iterations: int):
    """Phase 1: the root estimate of c on the subsample between the range ends `low` and
    `high` (c decreases with s; keep c(lo) > 0 >= c(hi)), Illinois regula falsi until the
    bracket is one grid `step` wide."""
    if low.value <= 0:
        return low.scale
    if high.value > 0:
        return high.scale
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
    return lo_s + (hi_s - lo_s) * lo_v / (lo_v - hi_v) if lo_v != hi_v else lo_s


def _confirm(evaluator: _Evaluator, on_all, grid: np.ndarray, estimate: float, noise: float):
    """Phase 2: evaluate all frames at the grid scales around `estimate`, walking outwards until
    c changes sign between them; (ŝ, clipped) of the fitted crossing, or None when the curve of
    all frames is not monotone within `noise`."""
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
    if is_monotone(scales, values, noise) and len(scales):
        return crossing(scales, decreasing_fit(values))
    return None


def _local_grid(evaluator, on_all, grid, all_frames, estimate, noise, local_steps, warnings):
    """The fallback: a local grid of +-`local_steps` on all frames around `estimate` (the full
    grid when the crossing leaves it); returns (ŝ, clipped)."""
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
    scale, clipped = crossing(scales, decreasing_fit(values))
    at_window_edge = clipped is not None and (
        (clipped == "low" and window[0] > grid[0]) or (clipped == "high" and window[-1] < grid[-1])
    )
    if at_window_edge:  # the crossing left the local window: the full grid decides
        warnings.append("the crossing is outside the local grid: evaluated the full grid")
        scale, clipped, _ = grid_search(evaluator, grid, all_frames, noise, phase="local-grid")
    return scale, clipped


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
    estimate = _illinois(on_subsample, low, high, step, max_iterations)
    sub_scales, sub_values = evaluator.curve("subsample")
    if is_monotone(sub_scales, sub_values, noise):
        confirmed = _confirm(evaluator, on_all, grid, estimate, noise)
        if confirmed is not None:
            scale, clipped = confirmed
            return scale, clipped, None, True, warnings
    scale, clipped = _local_grid(
        evaluator, on_all, grid, all_frames, estimate, noise, local_steps, warnings
    )
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
