"""KITTI-protocol average precision (R40 / R11, BEV and 3D) of predicted boxes against labels.

The protocol follows OpenPCDet's `kitti_object_eval_python` (the reference every DA paper uses):
per ground truth, in label order, the matching detection is chosen among unassigned detections
with overlap strictly above the IoU threshold; thresholds are 41 samples of the true-positive
scores; matching is redone at every threshold, preferring the largest overlap; precision is
max-interpolated from the right; AP_R40 is the mean of precision entries 1..40, AP_R11 of entries
0, 4, ..., 40. "Ignored" ground truths (Van for Car, outside the difficulty or range band, too few
points) and ignored detections (2D box too small, outside the band) neither count as misses nor
as false positives. Overlaps are float64 (dali_cli.geometry), not OpenPCDet's float32 kernel.

Everything is vectorized over frames. Where one detection overlaps several ground truths above the
threshold (possible only below IoU 0.5 or with overlapping labels), the connected group of boxes
around it is matched by a direct port of the reference loop, so results match it in every case.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dali_cli import geometry
from dali_cli.evaluation.curves import (  # noqa: F401  (re-exported: the evaluator's API)
    NUM_SAMPLE_POINTS,
    RECALL_POSITIONS,
    _average_precision,
    _average_precision_by_recall,
    _counts_at_levels,
    _Curve,
    _match_sequentially,
    _split_greedy_groups,
    _statistics,
    ap_ceiling,
    sample_points,
)
from dali_cli.evaluation.heading import heading_summary
from dali_cli.evaluation.image import (
    IMAGE_BOX_COLUMNS,
    REGION_LABELS,
    ImageMatches,
    has_image_boxes,
    image_matches,
    image_min_overlap,
)
from dali_cli.evaluation.tables import ceiling_notes, format_table  # noqa: F401 (re-exported)
from dali_cli.store.artifacts import BoxTable

DIFFICULTIES = ("easy", "moderate", "hard")
MIN_HEIGHT_PX = (40.0, 25.0, 25.0)
MAX_OCCLUSION = (0, 1, 2)
MAX_TRUNCATION = (0.15, 0.3, 0.5)
RANGE_BANDS_M = {
    "all": (0.0, math.inf),
    "0-30": (0.0, 30.0),
    "30-50": (30.0, 50.0),
    "50-80": (50.0, 80.0),
}
KITTI_GT_COLUMNS = ("truncated", "occluded", "bbox_top", "bbox_bottom")
PROTOCOLS = ("auto", "kitti", "range", "st3d")
# ground-truth classes that are ignored (neither miss nor false positive) for an evaluated class
SIMILAR_CLASSES = {"car": ("van",), "pedestrian": ("person_sitting",)}
# ST3D's target-domain evaluation: front field of view and the KITTI detection range
ST3D_FOV_DEG = 90.0
ST3D_RANGE_M = (0.0, -40.0, 70.4, 40.0)  # x_min, y_min, x_max, y_max of the box centre


class EvaluationError(ValueError):
    """Inputs that cannot be evaluated (the message names the frame and field)."""


# ---------------------------------------------------------------------------------------------
# Inputs: frames, pairs and overlaps


@dataclass
class _Boxes:
    """One side (predictions or ground truth), sorted by frame, table order kept within a frame."""

    frame: np.ndarray  # (n,) int64 frame code
    boxes: np.ndarray  # (n, 7) float64
    score: np.ndarray  # (n,) float64
    label: np.ndarray  # (n,) lower-case class names
    columns: dict[str, np.ndarray]  # the table's other columns, same order
    row: np.ndarray  # (n,) int64 the table row of each box


def _prepare(table: BoxTable, universe: np.ndarray) -> _Boxes:
    """Sort a table by frame; `universe` `(F,)` str lists the frames (their codes are indices)."""
    ids = table.frame_id.astype(str)
    sorter = np.argsort(universe)
    position = np.minimum(np.searchsorted(universe[sorter], ids), max(len(universe) - 1, 0))
    code = sorter[position] if len(universe) else np.zeros(0, np.int64)
    order = np.argsort(code, kind="stable")
    columns = {name: np.asarray(values)[order] for name, values in table.columns.items()}
    names, inverse = np.unique(np.asarray(table["label"], dtype=str), return_inverse=True)
    return _Boxes(
        frame=code[order].astype(np.int64),
        boxes=table.boxes[order],
        score=np.asarray(table["score"], dtype=np.float64)[order],
        label=np.char.lower(names)[inverse.reshape(-1)][order] if len(names) else ids[:0],
        columns=columns,
        row=order.astype(np.int64),
    )


def _same_frame_pairs(pred: _Boxes, gt: _Boxes, num_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Every (prediction, ground truth) index pair `(E,)` of the same frame."""
    gt_count = np.bincount(gt.frame, minlength=num_frames)
    gt_start = np.cumsum(gt_count) - gt_count
    per_pred = gt_count[pred.frame]  # (n_pred,) candidate ground truths of each prediction
    pred_index = np.repeat(np.arange(len(pred.frame)), per_pred)
    run_start = np.repeat(np.cumsum(per_pred) - per_pred, per_pred)
    gt_index = gt_start[pred.frame[pred_index]] + np.arange(len(pred_index)) - run_start
    return pred_index, gt_index


def _frame_pairs(pred: _Boxes, gt: _Boxes, num_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(prediction, ground truth) index pairs `(E,)` in the same frame whose BEV circles touch."""
    pred_index, gt_index = _same_frame_pairs(pred, gt, num_frames)
    pred_radius = 0.5 * np.hypot(pred.boxes[:, 3], pred.boxes[:, 4])  # bounding circles
    gt_radius = 0.5 * np.hypot(gt.boxes[:, 3], gt.boxes[:, 4])
    reach = pred_radius[pred_index] + gt_radius[gt_index]
    dx = pred.boxes[:, 0][pred_index] - gt.boxes[:, 0][gt_index]
    dy = pred.boxes[:, 1][pred_index] - gt.boxes[:, 1][gt_index]
    near = dx * dx + dy * dy <= (reach * (1 + 1e-9) + 1e-9) ** 2
    return pred_index[near], gt_index[near]


# ---------------------------------------------------------------------------------------------
# Ignore flags: -1 does not take part, 0 counts, 1 ignored (neither miss nor false positive)


def _gt_class_flags(gt: _Boxes, class_name: str) -> np.ndarray:
    """1 for the evaluated class, 0 for a similar class (Van for Car), -1 for any other."""
    similar = SIMILAR_CLASSES.get(class_name, ())
    return np.where(gt.label == class_name, 1, np.where(np.isin(gt.label, similar), 0, -1))


def _combine_gt(valid_class: np.ndarray, ignore: np.ndarray) -> np.ndarray:
    return np.where(
        (valid_class == 1) & ~ignore, 0, np.where((valid_class == 0) | (valid_class == 1), 1, -1)
    ).astype(np.int8)


def _combine_pred(same_class: np.ndarray, ignore: np.ndarray) -> np.ndarray:
    # the reference checks the size filter before the class: small boxes are ignored either way
    return np.where(ignore, 1, np.where(same_class, 0, -1)).astype(np.int8)


def _as_written(values: np.ndarray) -> np.ndarray:
    """float64 of the decimal text that float32 KITTI fields came from (labels carry 2 decimals).

    The reference parses label text as float64: truncation 0.15 must pass `<= 0.15`, which the
    float32 value 0.150000006 would not.
    """
    values = np.asarray(values)
    wide = values.astype(np.float64)
    if values.dtype != np.float32:
        return wide
    rounded = np.round(wide, 2)
    return np.where(rounded.astype(np.float32) == values, rounded, wide)


def _box_height_px(columns: dict[str, np.ndarray], count: int, absolute: bool) -> np.ndarray:
    """2D box heights `(n,)` in pixels; the reference takes |h| for detections only."""
    if "bbox_top" in columns and "bbox_bottom" in columns:
        height = _as_written(columns["bbox_bottom"]) - _as_written(columns["bbox_top"])
        return np.abs(height) if absolute else height
    return np.full(count, np.inf)  # no 2D boxes (LiDAR-only predictions): no size filter


def _difficulty_flags(
    pred: _Boxes, gt: _Boxes, class_name: str, level: int, few_points: np.ndarray
):
    valid_class = _gt_class_flags(gt, class_name)
    height = _box_height_px(gt.columns, len(gt.frame), absolute=False)
    ignore = (
        (gt.columns["occluded"].astype(np.float64) > MAX_OCCLUSION[level])
        | (_as_written(gt.columns["truncated"]) > MAX_TRUNCATION[level])
        | (height <= MIN_HEIGHT_PX[level])
        | few_points
    )
    pred_small = _box_height_px(pred.columns, len(pred.frame), True) < MIN_HEIGHT_PX[level]
    return _combine_gt(valid_class, ignore), _combine_pred(pred.label == class_name, pred_small)


def _band_flags(pred: _Boxes, gt: _Boxes, class_name: str, band: tuple, few_points: np.ndarray):
    low, high = band
    gt_range = np.hypot(gt.boxes[:, 0], gt.boxes[:, 1])
    pred_range = np.hypot(pred.boxes[:, 0], pred.boxes[:, 1])
    gt_out = (gt_range < low) | (gt_range >= high)
    pred_out = (pred_range < low) | (pred_range >= high)
    return (
        _combine_gt(_gt_class_flags(gt, class_name), gt_out | few_points),
        _combine_pred(pred.label == class_name, pred_out),
    )


# ---------------------------------------------------------------------------------------------
# Public API


def has_kitti_columns(table: BoxTable) -> bool:
    """Whether a box table carries the KITTI label fields the difficulty filters need."""
    return all(name in table.columns for name in KITTI_GT_COLUMNS)


def _frame_universe(pred: BoxTable, gt: BoxTable, frame_ids) -> np.ndarray:
    """The evaluated frame ids `(F,)` str; every box must belong to one of them."""
    named = np.unique(np.r_[pred.frame_id.astype(str), gt.frame_id.astype(str)])
    if frame_ids is None:
        return named
    universe = np.asarray([str(f) for f in frame_ids], dtype=str)
    if len(np.unique(universe)) != len(universe):
        raise EvaluationError("the list of evaluated frames has duplicates")
    outside = named[~np.isin(named, universe)]
    if len(outside):
        raise EvaluationError(
            f"boxes of frame '{outside[0]}' ({len(outside)} such frames) lie outside the evaluated frames"
        )
    return universe


def in_st3d_region(
    table: BoxTable, fov_deg: float = ST3D_FOV_DEG, range_m: tuple = ST3D_RANGE_M
) -> np.ndarray:
    """`(N,)` bool: box centre inside the front FOV (|atan2(y, x)| < fov/2) and the range."""
    boxes = table.boxes
    angle = np.arctan2(boxes[:, 1], boxes[:, 0])
    half = math.radians(fov_deg) / 2
    x_min, y_min, x_max, y_max = range_m
    return (
        (angle > -half)
        & (angle < half)
        & (boxes[:, 0] >= x_min)
        & (boxes[:, 0] <= x_max)
        & (boxes[:, 1] >= y_min)
        & (boxes[:, 1] <= y_max)
    )


def _st3d_ground_truth(gt: BoxTable, fov_deg: float, range_m: tuple) -> BoxTable:
    """ST3D's target ground truth: boxes outside the front FOV or the range are dropped, and
    every box gets the 2D box [0, 0, 50, 50], no occlusion and no truncation."""
    kept = gt.select(in_st3d_region(gt, fov_deg, range_m))
    count = len(kept)
    return kept.with_columns(
        truncated=np.zeros(count, np.float32),
        occluded=np.zeros(count, np.int32),
        bbox_top=np.zeros(count, np.float32),
        bbox_bottom=np.full(count, 50.0, np.float32),
    )


def evaluate(
    pred: BoxTable,
    gt: BoxTable,
    iou: float = 0.7,
    recall_positions: int = 40,
    protocol: str = "auto",
    class_name: str = "Car",
    min_gt_points: int = 0,
    frame_ids: list[str] | None = None,
    st3d_fov_deg: float = ST3D_FOV_DEG,
    st3d_range_m: tuple = ST3D_RANGE_M,
    front_only: bool = False,
    scored: Scored | None = None,
) -> dict:
    """AP_BEV and AP_3D (percent) of `pred` against `gt`, in the metrics.json shape.

    protocol: "kitti" (easy/moderate/hard from the KITTI label columns), "range" (all boxes and
    the bands 0-30, 30-50, 50-80 m of BEV distance), "st3d" (ST3D's target evaluation: ground
    truth only in the front FOV and range, all boxes easy, so easy = moderate = hard), or "auto"
    (kitti when `gt` has the KITTI columns, else range). Ground-truth boxes of the class with fewer
    than `min_gt_points` points (column num_points) are ignored, not dropped. `frame_ids`: the
    evaluated frames (default: every frame named by either table; frames without boxes count).
    `front_only`: drop ground truth and predictions centred outside the st3d region (front FOV
    and detection range) before any protocol, as if the clouds were FOV-cropped like KITTI's; with
    "range" this gives the bands of the front region, with "st3d" it also drops predictions there.
    `scored`: `scored_boxes` of the same arguments when the caller has it (the overlaps do not
    depend on `iou`: several thresholds and the error breakdown share one computation).
    """
    protocol = _checked_protocol(gt, iou, recall_positions, protocol)
    if scored is None:
        scored = scored_boxes(
            pred, gt, protocol, class_name, min_gt_points, frame_ids, front_only, st3d_fov_deg,
            st3d_range_m,
        )  # fmt: skip
    pred_boxes, gt_boxes, pairs = scored.pred, scored.gt, scored.pairs
    bev, volume = scored.overlap["bev"], scored.overlap["3d"]
    result = {
        "iou": float(iou),
        "recall_positions": int(recall_positions),
        "protocol": protocol,
        "frames": int(len(scored.frame_ids)),
        "min_gt_points": int(min_gt_points),
        "front_only": bool(front_only),
        "bev": {},
        "3d": {},
        "aos": {},
        # where AOS is matched: "image" (KITTI's devkit: 2D boxes, alpha) or "bev" (yaw)
        "aos_matching": "image" if scored.image is not None else "bev",
        **({"bbox": {}, "bbox_iou": image_min_overlap(class_name)} if scored.image else {}),
        "aph": {},
        "heading": {},
        "counts": {},
        "curves": {"bev": {}, "3d": {}},
    }
    for name, (ignored_gt, ignored_pred) in scored.flags.items():
        counts = {
            "gt": int(np.sum(ignored_gt == 0)),
            "gt_ignored": int(np.sum(ignored_gt == 1)),
            "pred": int(np.sum(ignored_pred == 0)),
        }
        for metric, overlap in (("bev", bev), ("3d", volume)):
            curve = _statistics(
                pred_boxes, gt_boxes, pairs, overlap, ignored_gt, ignored_pred, iou,
                sample_points(recall_positions), heading="aos" if metric == "bev" else None,
            )  # fmt: skip
            value, detail = _average_precision(curve, recall_positions)
            result[metric][name] = value
            result["curves"][metric][name] = detail
            counts[metric] = curve.totals
            if metric == "bev":  # the heading metrics (docs/evaluation.md)
                result["aos"][name] = _average_precision(curve, recall_positions, True)[0]
                if scored.image is not None:  # KITTI's AOS: on the image matches, alpha
                    image, min_overlap = scored.image, image_min_overlap(class_name)
                    on_image = _statistics(
                        pred_boxes, gt_boxes, image.pairs, image.overlap, ignored_gt,
                        image.ignored_pred(ignored_gt, ignored_pred, min_overlap), min_overlap,
                        sample_points(recall_positions), heading="aos",
                        yaw=(image.pred_alpha, image.gt_alpha),
                    )  # fmt: skip
                    result["bbox"][name] = _average_precision(on_image, recall_positions)[0]
                    result["aos"][name] = _average_precision(on_image, recall_positions, True)[0]
                aph = _statistics(
                    pred_boxes, gt_boxes, pairs, overlap, ignored_gt, ignored_pred, iou,
                    sample_points(recall_positions), heading="aph",
                )  # fmt: skip
                result["aph"][name] = _average_precision(aph, recall_positions, True)[0]
        matched = matched_ground_truth(scored, "bev", name, iou)
        true = (matched >= 0) & (ignored_pred == 0)
        true[true] = ignored_gt[matched[true]] == 0
        result["heading"][name] = heading_summary(
            pred_boxes.boxes[true, 6], gt_boxes.boxes[matched[true], 6]
        )
        counts["ap_ceiling"] = ap_ceiling(counts["gt"], recall_positions)
        result["counts"][name] = counts
    if protocol == "st3d":
        sections = ("bev", "3d", "aos", "aph", "heading", "counts")
        for section in (*(result[key] for key in sections), *result["curves"].values()):
            for name in DIFFICULTIES[1:]:
                section[name] = section[DIFFICULTIES[0]]
    return {class_name: result}


@dataclass
class Scored:
    """The boxes one evaluation scores: both tables after the protocol's restriction, in the
    evaluator's order (by frame, table order within a frame), their candidate pairs with BEV and
    3D overlaps, and the ignore flags of every difficulty or band."""

    protocol: str  # resolved ("auto" never)
    frame_ids: np.ndarray  # (F,) str evaluated frames
    pred_table: BoxTable  # predictions after the protocol's restriction (rows: `pred.row`)
    gt_table: BoxTable
    pred: _Boxes  # (P,) boxes in the evaluator's order
    gt: _Boxes  # (G,)
    pairs: tuple[np.ndarray, np.ndarray]  # (E,) prediction and ground-truth indices, same frame
    overlap: dict[str, np.ndarray]  # {"bev", "3d"}: (E,) float64 IoU of each pair
    # group -> (ignored_gt (G,), ignored_pred (P,)) int8: -1 takes no part, 0 counts, 1 ignored
    flags: dict[str, tuple[np.ndarray, np.ndarray]]
    # KITTI's image side when both tables carry image boxes and alpha (image.py), else None
    image: ImageMatches | None = None


def _image_matches(pred: _Boxes, gt: _Boxes, num_frames: int) -> ImageMatches:
    """The image side (image.py) of every same-frame pair of two tables with image boxes."""

    def boxes(side: _Boxes) -> np.ndarray:
        return np.stack([_as_written(side.columns[name]) for name in IMAGE_BOX_COLUMNS], axis=1)

    return image_matches(
        boxes(pred), boxes(gt), _same_frame_pairs(pred, gt, num_frames),
        np.isin(gt.label, REGION_LABELS),
        np.asarray(pred.columns["alpha"], np.float64), np.asarray(gt.columns["alpha"], np.float64),
    )  # fmt: skip


def scored_boxes(
    pred: BoxTable,
    gt: BoxTable,
    protocol: str = "auto",
    class_name: str = "Car",
    min_gt_points: int = 0,
    frame_ids: list[str] | None = None,
    front_only: bool = False,
    st3d_fov_deg: float = ST3D_FOV_DEG,
    st3d_range_m: tuple = ST3D_RANGE_M,
) -> Scored:
    """What `evaluate` (same arguments) scores, before any threshold: see `Scored`."""
    protocol = _checked_protocol(gt, 0.0, RECALL_POSITIONS[0], protocol)
    pred, gt = _restricted(pred, gt, protocol, front_only, st3d_fov_deg, st3d_range_m)
    universe = _frame_universe(pred, gt, frame_ids)
    pred_boxes, gt_boxes = _prepare(pred, universe), _prepare(gt, universe)
    pairs = _frame_pairs(pred_boxes, gt_boxes, len(universe))
    bev, volume = geometry.iou_pairs_bev_3d(pred_boxes.boxes[pairs[0]], gt_boxes.boxes[pairs[1]])
    image = None
    if protocol == "kitti" and has_image_boxes(pred) and has_image_boxes(gt):
        image = _image_matches(pred_boxes, gt_boxes, len(universe))
    return Scored(
        protocol=protocol,
        frame_ids=universe,
        pred_table=pred,
        gt_table=gt,
        pred=pred_boxes,
        gt=gt_boxes,
        pairs=pairs,
        overlap={"bev": bev, "3d": volume},
        flags=_groups(pred_boxes, gt_boxes, class_name.lower(), protocol, min_gt_points),
        image=image,
    )


def matched_ground_truth(scored: Scored, metric: str, group: str, iou: float) -> np.ndarray:
    """`(P,)` int64: the ground truth (index into `scored.gt`) each prediction is matched to with
    every prediction kept, -1 for none: the matching behind `counts` (per ground truth in label
    order, the unassigned prediction with the largest `metric` overlap above `iou`, counted
    predictions before ignored ones). True positives: matched, both flags 0; false positives:
    flag 0 and unmatched; misses: counted ground truths no prediction is matched to."""
    ignored_gt, ignored_pred = scored.flags[group]
    pred_index, gt_index = scored.pairs
    overlap = scored.overlap[metric]
    keep = (overlap > iou) & (ignored_gt[gt_index] != -1) & (ignored_pred[pred_index] != -1)
    num_pred = len(scored.pred.frame)
    fast, components, _, _ = _split_greedy_groups(
        pred_index[keep], gt_index[keep], overlap[keep], num_pred, len(scored.gt.frame)
    )
    pred_index, gt_index, overlap = fast  # each prediction a candidate of one ground truth
    rank = np.where(ignored_pred[pred_index] == 0, -overlap, 0.0)
    order = np.lexsort((pred_index, rank, ignored_pred[pred_index], gt_index))
    first = order[np.r_[True, gt_index[order][1:] != gt_index[order][:-1]]] if len(order) else order
    matched = np.full(num_pred, -1, dtype=np.int64)
    matched[pred_index[first]] = gt_index[first]
    for component in components:
        loop = _match_sequentially(
            component, scored.pred.score, ignored_gt, ignored_pred, -math.inf, True
        )
        for gt, chosen in loop[4]:
            matched[chosen] = gt
    return matched


def average_precision(
    scored: Scored, metric: str, group: str, iou: float, recall_positions: int = 40
) -> float | None:
    """AP in percent of one overlap kind ("bev", "3d") and group of `scored` at `iou`: what
    `evaluate` reports there, without the other kind and groups."""
    ignored_gt, ignored_pred = scored.flags[group]
    curve = _statistics(
        scored.pred, scored.gt, scored.pairs, scored.overlap[metric], ignored_gt, ignored_pred,
        iou, sample_points(recall_positions),
    )  # fmt: skip
    return _average_precision(curve, recall_positions)[0]


def _checked_protocol(gt: BoxTable, iou: float, recall_positions: int, protocol: str) -> str:
    """The protocol to run ("auto" resolved); EvaluationError for a parameter it cannot take."""
    if recall_positions not in RECALL_POSITIONS:
        raise EvaluationError(
            f"recall_positions must be one of {', '.join(map(str, RECALL_POSITIONS))}, "
            f"got {recall_positions}"
        )
    if protocol not in PROTOCOLS:
        raise EvaluationError(f"unknown protocol '{protocol}' (choose from {', '.join(PROTOCOLS)})")
    if not 0.0 <= iou < 1.0:
        raise EvaluationError(f"iou must be in [0, 1), got {iou}")
    if protocol == "auto":
        protocol = "kitti" if has_kitti_columns(gt) else "range"
    if protocol == "kitti" and not has_kitti_columns(gt):
        missing = [name for name in KITTI_GT_COLUMNS if name not in gt.columns]
        raise EvaluationError(f"ground truth lacks the KITTI columns {', '.join(missing)}")
    return protocol


def _restricted(pred, gt, protocol, front_only, fov_deg, range_m) -> tuple[BoxTable, BoxTable]:
    """(pred, gt) restricted to the front region (`front_only`) and, for st3d, its ground truth
    with every prediction given the same (easy) 2D box."""
    if front_only:
        gt = gt.select(in_st3d_region(gt, fov_deg, range_m))
        pred = pred.select(in_st3d_region(pred, fov_deg, range_m))
    if protocol == "st3d":
        gt = _st3d_ground_truth(gt, fov_deg, range_m)
        pred = pred.with_columns(
            bbox_top=np.zeros(len(pred), np.float32),
            bbox_bottom=np.full(len(pred), 50.0, np.float32),
        )
    return pred, gt


def _groups(pred_boxes, gt_boxes, class_key: str, protocol: str, min_gt_points: int) -> dict:
    """Per range band or difficulty: the (ignored_gt, ignored_pred) flags of the evaluation."""
    gt_points = np.asarray(gt_boxes.columns["num_points"])
    if min_gt_points > 0 and len(gt_points) and not gt_points.any():
        raise EvaluationError(
            "min_gt_points needs ground-truth point counts, but num_points is all 0"
        )
    few_points = gt_points < min_gt_points
    if protocol == "range":
        return {
            name: _band_flags(pred_boxes, gt_boxes, class_key, band, few_points)
            for name, band in RANGE_BANDS_M.items()
        }
    # st3d gives every box the same 2D box: the three levels coincide, compute one
    levels = DIFFICULTIES[:1] if protocol == "st3d" else DIFFICULTIES
    return {
        name: _difficulty_flags(pred_boxes, gt_boxes, class_key, level, few_points)
        for level, name in enumerate(levels)
    }


def check_ious(ious: tuple[float, ...]) -> None:
    """ParameterError for an IoU threshold outside [0, 1) or one given twice."""
    from dali_cli.runtime.errors import ParameterError

    for iou in ious:
        if not 0.0 <= iou < 1.0:
            raise ParameterError("ious", f"must be in [0, 1), got {iou}")
    if len(set(ious)) != len(ious):
        raise ParameterError("ious", f"repeated threshold in {list(ious)}")


@dataclass(frozen=True)
class Protocol:
    """How `evaluate` scores one table (its keyword arguments, `dali compare`'s settings)."""

    iou: float = 0.7
    recall_positions: int = 40
    protocol: str = "auto"
    class_name: str = "Car"
    min_gt_points: int = 0
    front_only: bool = False
