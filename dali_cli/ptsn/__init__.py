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

The package: `spec` (scale range, E_est specs, errors, the Predictor protocol), `stats` (E_pred
and the criterion), `cache` (DetectionCache), `search` (find_scale: grid and bracket), `frames`
(frame selection, the bracket's subsample, the crop to the detector's view), `detections` (the
sweep's boxes kept, E_pred(ŝ) over a stricter score cut from them). I/O is the stage's
(`stages.ptsn_sweep`, `dali_cli.store.scale_file`); the sweep plot is the report's
(`dali_cli.reporting.plots.plot_sweep`).
"""

from dali_cli.ptsn.cache import DetectionCache
from dali_cli.ptsn.frames import (
    FRAME_CAP,
    crop_for_scales,
    select_frames,
    subsample_for_bracket,
)
from dali_cli.ptsn.search import (
    Evaluation,
    SearchResult,
    bracket_search,
    crossing,
    decreasing_fit,
    find_scale,
    grid_search,
    is_monotone,
)
from dali_cli.ptsn.spec import (
    DEFAULT_ROS_FACTOR,
    DEFAULT_STEP,
    NO_DETECTIONS_ADVICE,
    NO_DETECTIONS_POLICIES,
    SCALE_DECIMALS,
    NoDetectionsError,
    Predictor,
    PTSNError,
    ScaleRange,
    parse_scale_range,
    parse_size,
    ros_expected_size,
)
from dali_cli.ptsn.stats import (
    SizeStats,
    criterion,
    expected_prediction,
    expected_prediction_by_frame,
)

__all__ = [
    "DEFAULT_ROS_FACTOR",
    "DEFAULT_STEP",
    "NO_DETECTIONS_ADVICE",
    "NO_DETECTIONS_POLICIES",
    "SCALE_DECIMALS",
    "DetectionCache",
    "Evaluation",
    "NoDetectionsError",
    "PTSNError",
    "Predictor",
    "ScaleRange",
    "SearchResult",
    "SizeStats",
    "bracket_search",
    "criterion",
    "crop_for_scales",
    "crossing",
    "decreasing_fit",
    "expected_prediction",
    "expected_prediction_by_frame",
    "find_scale",
    "grid_search",
    "is_monotone",
    "parse_scale_range",
    "parse_size",
    "ros_expected_size",
    "select_frames",
    "FRAME_CAP",
    "subsample_for_bracket",
]
