"""Per-dimension size correction of pseudo labels after PTSN.

PTSN scales the target cloud by one isotropic ŝ, chosen so that the *volume* of the mean predicted
size matches E_est. When the source/target size ratios differ per dimension (Waymo/KITTI: l 1.20,
w 1.29, h 1.14), a bias remains in each dimension at ŝ (measured: w +0.12 m, h -0.08 m), PPCG
then makes the points agree with the biased boxes and retraining learns the bias. This module
removes it with one factor per dimension, factor_d = E_est_d / E_pred_d, where E_pred is the mean
size of the pseudo boxes themselves (paper Eq. 1, the same mean PTSN uses) and E_est is PTSN's
expected size (SN statistics, ROS or given): target statistics only, never target labels.

Each box keeps its heading, its centre in x, y and its **bottom face**: z moves by half the change
of h. Boxes come from a detector run about the ground (PTSN scales points about the ground plane,
so the ground stays put), and a car's contact with the ground is pinned by the ground points around
it, whereas its height is what the size bias got wrong; keeping the centre instead would lift
shrunk cars off the road or push grown ones into it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dali_cli.labels import SCORE_MIN
from dali_cli.ptsn.stats import expected_prediction_by_frame

METHODS = ("per-dim", "none")


@dataclass
class SizeCorrection:
    """The correction applied: factors (3,) l, w, h; mean sizes (3,) in metres before and after
    (over the boxes with score >= score_min, `mean` as in PTSN); how many boxes defined them."""

    method: str
    factors: np.ndarray
    mean_before: np.ndarray
    mean_after: np.ndarray
    e_est: np.ndarray
    boxes_used: int
    score_min: float
    mean: str

    def to_dict(self) -> dict:
        def listed(values: np.ndarray) -> list[float | None]:
            return [round(float(v), 6) if np.isfinite(v) else None for v in values]

        return {
            "method": self.method,
            "factors_lwh": listed(self.factors),
            "mean_lwh_before": listed(self.mean_before),
            "mean_lwh_after": listed(self.mean_after),
            "E_est": listed(self.e_est),
            "boxes_used": self.boxes_used,
            "score_min": self.score_min,
            "mean": self.mean,
            "anchor": "bottom face (z moves by half the change of h)",
        }


def resize_keeping_bottom(boxes: np.ndarray, factors: np.ndarray) -> np.ndarray:
    """boxes (N, 7) x, y, z, l, w, h, yaw with l, w, h multiplied by `factors` (3,) or (N, 3);
    x, y, yaw and the bottom face z - h/2 unchanged. Returns a new (N, 7) float64 array."""
    boxes = np.array(boxes, np.float64, copy=True).reshape(-1, 7)
    new_h = boxes[:, 5] * np.broadcast_to(np.asarray(factors, np.float64), (len(boxes), 3))[:, 2]
    boxes[:, 2] += (new_h - boxes[:, 5]) / 2  # bottom face z - h/2 stays put
    boxes[:, 3:6] *= factors
    return boxes


def mean_size(boxes: np.ndarray, frame_ids: np.ndarray, mean: str = "per-frame") -> np.ndarray:
    """Mean l, w, h (3,) of boxes (N, 7) grouped by frame_ids (N,) as PTSN's E_pred (NaN if none)."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    return expected_prediction_by_frame(boxes[:, 3:6], frame_ids, mean).mean_lwh


def correct_sizes(
    boxes: np.ndarray,
    scores: np.ndarray,
    frame_ids: np.ndarray,
    e_est: np.ndarray,
    *,
    score_min: float = SCORE_MIN,
    mean: str = "per-frame",
    method: str = "per-dim",
) -> tuple[np.ndarray, SizeCorrection]:
    """Remove the per-dimension bias of pseudo boxes against E_est.

    boxes (N, 7) float64 sensor frame, scores (N,), frame_ids (N,) str, e_est (3,) metres.
    factor_d = E_est_d / mean_d, the mean (per-frame or pooled, as PTSN) taken over boxes with
    score >= score_min; every box is resized by the same factors (`resize_keeping_bottom`).
    Since each mean is linear in the sizes, the corrected mean equals E_est exactly.
    method "none" returns the boxes unchanged (factors 1) and records the means.
    Returns (corrected boxes (N, 7), SizeCorrection). Raises ValueError on a bad method or E_est.
    """
    if method not in METHODS:
        raise ValueError(f"size correction must be one of {', '.join(METHODS)}, got {method!r}")
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    scores = np.asarray(scores, np.float64).reshape(-1)
    frame_ids = np.asarray(frame_ids)
    e_est = np.asarray(e_est, np.float64).reshape(3)
    if not (np.isfinite(e_est).all() and (e_est > 0).all()):
        raise ValueError(f"E_est must be three positive sizes in metres, got {e_est.tolist()}")
    used = scores >= score_min
    before = mean_size(boxes[used], frame_ids[used], mean)
    factors = np.ones(3)
    if method == "per-dim" and np.isfinite(before).all():
        factors = e_est / before
    corrected = resize_keeping_bottom(boxes, factors)
    after = mean_size(corrected[used], frame_ids[used], mean)
    record = SizeCorrection(
        method, factors, before, after, e_est, int(used.sum()), float(score_min), mean
    )
    return corrected, record


def factors_from_sweep(e_est, e_pred, where: str) -> np.ndarray:
    """Test-time factors (3,) l, w, h = E_est / E_pred(ŝ) of one ptsn-sweep (its scale.json's
    "E_est" and "E_pred_at_scale": the sweep's own label-free numbers on the unlabelled target
    training frames, so the correction reads no target label). ValueError naming `where` when
    either is missing or not three positive sizes."""
    values = {}
    for name, value in (("E_est", e_est), ("E_pred_at_scale", e_pred)):
        triple = np.asarray([np.nan if v is None else v for v in (value or ())], np.float64)
        if triple.shape != (3,) or not (np.isfinite(triple).all() and (triple > 0).all()):
            raise ValueError(
                f"{where}: field '{name}' must be three positive sizes in metres for a size "
                f"correction, got {value!r}"
            )
        values[name] = triple
    return values["E_est"] / values["E_pred_at_scale"]


def correct_class_sizes(
    boxes: np.ndarray, labels: np.ndarray, class_name: str, factors
) -> np.ndarray:
    """boxes (N, 7) with the rows labelled `class_name` resized by `factors` (3,)
    (`resize_keeping_bottom`), the others unchanged. Returns a new (N, 7) float64 array."""
    boxes = np.array(boxes, np.float64, copy=True).reshape(-1, 7)
    rows = np.asarray(labels) == class_name
    boxes[rows] = resize_keeping_bottom(boxes[rows], factors)
    return boxes
