"""The sweep's detections, kept: every box the detector found at the scales evaluated on all
frames (score >= the sweep's score_min), so that E_pred(ŝ) can be recomputed later over a
stricter score cut without a detector pass.

Why: E_pred(ŝ) of scale.json is the mean over every box above the sweep's cut, false ones
included. The test-time size correction (`dali eval --size-correction per-dim`) divides E_est by
it; where low-score false boxes have another mean size than the found cars, the factors move true
boxes off (docs/evaluation.md). `e_pred_at` gives E_pred(ŝ) over the confident boxes
only, computed exactly as the sweep computes its own (the per-frame or pooled mean of
`stats.expected_prediction` at each all-frames scale, linear between them as
`search._Evaluator.lwh_at`): at the sweep's own cut it reproduces "E_pred_at_scale".

The table (`detections.parquet` of a ptsn-sweep directory): one row per box, columns
scale float64 (the evaluated scale, rounded as the cache keys it), frame int64 (index in the target
frame set), l, w, h float64 (metres, de-scaled), score float32. Label-free: it holds only what the
detector predicted on the unlabelled target frames.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from dali_cli.ptsn.cache import DetectionCache
from dali_cli.ptsn.search import Evaluation
from dali_cli.ptsn.stats import expected_prediction_by_frame

DETECTIONS_NAME = "detections.parquet"  # in a ptsn-sweep directory, beside scale.json
COLUMNS = ("scale", "frame", "l", "w", "h", "score")


def all_frame_scales(evaluations: Sequence[Evaluation]) -> list[float]:
    """The scales (sorted) a search evaluated on all frames: those E_pred(ŝ) is interpolated from."""
    return sorted({e.scale for e in evaluations if e.subset == "all"})


def detection_columns(
    cache: DetectionCache, scales: Sequence[float], frames: Sequence[int]
) -> dict[str, np.ndarray]:
    """The cached boxes of `frames` (indices) at each of `scales` as the COLUMNS of the table
    (each (B,)); the detections are the cache's (a scale not yet run on a frame is run)."""
    parts: dict[str, list[np.ndarray]] = {name: [] for name in COLUMNS}
    for scale in scales:
        key = DetectionCache.key(scale)
        for frame, (boxes, scores) in zip(frames, cache.detections(key, frames), strict=True):
            count = len(boxes)
            parts["scale"].append(np.full(count, key, np.float64))
            parts["frame"].append(np.full(count, int(frame), np.int64))
            for d, name in enumerate("lwh"):
                parts[name].append(np.asarray(boxes[:, 3 + d], np.float64))
            parts["score"].append(np.asarray(scores, np.float32))
    dtypes = {"frame": np.int64, "score": np.float32}
    return {
        name: np.concatenate(values) if values else np.zeros(0, dtypes.get(name, np.float64))
        for name, values in parts.items()
    }


def e_pred_at(
    columns: dict[str, np.ndarray], scale: float, score_min: float, mean: str = "per-frame"
) -> tuple[np.ndarray, int]:
    """E_pred (3,) l, w, h in metres at `scale` over the boxes with score >= `score_min`, and how
    many boxes that is at the nearest evaluated scale (the count that speaks for the mean).

    columns: the table's COLUMNS. At each evaluated scale E_pred is `expected_prediction` of the
    kept boxes grouped by frame (`mean` "per-frame" or "pooled", as the sweep's); between scales
    it is linear, outside them it is the nearest end's (np.interp). NaN (3,) and 0 when no
    evaluated scale keeps a box.
    """
    keep = np.asarray(columns["score"], np.float64) >= score_min
    scales = np.asarray(columns["scale"], np.float64)[keep]
    frames = np.asarray(columns["frame"], np.int64)[keep]
    sizes = np.stack([np.asarray(columns[name], np.float64)[keep] for name in "lwh"], axis=1)
    found, means, counts = [], [], []
    for value in np.unique(scales):
        at = scales == value
        found.append(value)
        means.append(expected_prediction_by_frame(sizes[at], frames[at], mean).mean_lwh)
        counts.append(int(at.sum()))
    if not found:
        return np.full(3, np.nan), 0
    lwh = np.stack(means)  # (K, 3), every row defined: each scale kept at least one box
    result = np.array([np.interp(scale, found, lwh[:, d]) for d in range(3)])
    return result, counts[int(np.argmin(np.abs(np.asarray(found) - scale)))]
