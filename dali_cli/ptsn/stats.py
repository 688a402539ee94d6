"""E_pred: the mean predicted car size at a scale (paper Eq. 1) and the matching criterion c(s)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


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


def expected_prediction_by_frame(
    sizes: np.ndarray, frame_ids: np.ndarray, mean: str = "per-frame"
) -> SizeStats:
    """`expected_prediction` of sizes `(N, 3)` (l, w, h) grouped by their frame ids `(N,)` (any
    hashable labels; frames without boxes do not appear, as they do not count)."""
    sizes = np.asarray(sizes, np.float64).reshape(-1, 3)
    _, frame_of_box = np.unique(np.asarray(frame_ids), return_inverse=True)
    order = np.argsort(frame_of_box, kind="stable")
    starts = np.flatnonzero(np.diff(frame_of_box[order])) + 1
    return expected_prediction(np.split(sizes[order], starts) if len(sizes) else [], mean)


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
