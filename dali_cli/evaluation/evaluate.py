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
from dali_cli.evaluation.heading import heading_summary, heading_weight
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
NUM_SAMPLE_POINTS = 41  # the reference's score thresholds: R40 and R11 share them
# recall grids: KITTI's R40 (the reported metric), R11 (KITTI before 2019) and a fine R400 (not a
# KITTI metric): R40 steps by precision / 40 (about 2 points) when a maximum recall crosses a k/40
# boundary, R400 by a tenth of that (docs/evaluation.md)
RECALL_POSITIONS = (40, 11, 400)


def sample_points(recall_positions: int) -> int | None:
    """The number of score thresholds (recall samples, 0 included) of an AP_R<recall_positions>:
    the reference's 41 for R40 and R11; None for R400, which thresholds at every true-positive
    score and reads the precision at the recall values k/400 (the reference's sampling indexes
    recall positions by threshold count, right only when far more cars count than positions)."""
    return NUM_SAMPLE_POINTS if recall_positions in (11, 40) else None


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


def _frame_pairs(pred: _Boxes, gt: _Boxes, num_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(prediction, ground truth) index pairs `(E,)` in the same frame whose BEV circles touch."""
    gt_count = np.bincount(gt.frame, minlength=num_frames)
    gt_start = np.cumsum(gt_count) - gt_count
    per_pred = gt_count[pred.frame]  # (n_pred,) candidate ground truths of each prediction
    pred_index = np.repeat(np.arange(len(pred.frame)), per_pred)
    run_start = np.repeat(np.cumsum(per_pred) - per_pred, per_pred)
    gt_index = gt_start[pred.frame[pred_index]] + np.arange(len(pred_index)) - run_start
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
# Matching statistics


def _sample_thresholds(
    tp_scores: np.ndarray, num_gt: int, points: int = NUM_SAMPLE_POINTS
) -> np.ndarray:
    """Score thresholds at (about) `points` evenly spaced recalls: the reference's get_thresholds
    (41 points)."""
    scores = np.sort(np.asarray(tp_scores, dtype=np.float64))[::-1]
    count = len(scores)
    if count == 0 or num_gt == 0:
        return np.zeros(0)
    left = (np.arange(count) + 1) / num_gt  # recall if this score is the threshold
    right = np.r_[left[1:], left[-1]]  # next score's recall (i + 2) / num_gt; the last: its own
    chosen, current, start = [], 0.0, 0
    while start < count and len(chosen) < points:
        # first index at or after `start` whose recall is closest to the current target
        accept = ~((right[start:] - current) < (current - left[start:]))
        accept[-1] = True
        index = start + int(np.argmax(accept))
        chosen.append(scores[index])
        current += 1 / (points - 1.0)  # accumulated like the reference, not k / 40
        start = index + 1
    return np.asarray(chosen)


def ap_ceiling(num_gt: int, recall_positions: int = 40) -> float | None:
    """The AP (percent) of a perfect detector when `num_gt` ground truths count: under R40 and
    R11 below 100 when fewer than 41 count, since the reference indexes the recall positions by
    threshold count (one threshold per true positive there: 22 cars cap AP_R40 at 52.5); 100
    under R400; None without counted ground truth (docs/evaluation.md)."""
    if num_gt <= 0:
        return None
    if recall_positions == 400:
        return 100.0
    count = len(_sample_thresholds(np.arange(num_gt, 0, -1, dtype=np.float64), num_gt))
    precision = (np.arange(NUM_SAMPLE_POINTS) < count).astype(np.float64)  # 1 where sampled
    entries = precision[1:] if recall_positions == 40 else precision[::4]
    return float(entries.sum() / len(entries) * 100)


def _edge_components(pred_index: np.ndarray, gt_index: np.ndarray, num_pred: int, num_gt: int):
    """Connected-component label `(E,)` of each (prediction, ground truth) edge: label
    propagation, a few vectorized rounds because components hold a handful of boxes."""
    gt_label = np.arange(num_gt)
    pred_label = np.full(num_pred, num_gt)
    while True:
        edge_label = np.minimum(gt_label[gt_index], pred_label[pred_index])
        new_gt, new_pred = gt_label.copy(), pred_label.copy()
        np.minimum.at(new_gt, gt_index, edge_label)
        np.minimum.at(new_pred, pred_index, edge_label)
        if np.array_equal(new_gt, gt_label) and np.array_equal(new_pred, pred_label):
            return edge_label
        gt_label, pred_label = new_gt, new_pred


@dataclass
class _Component:
    """Ground truths (ascending) with their candidate predictions, matched greedily in order."""

    gts: list[int]
    candidates: list[list[tuple[int, float]]]  # per ground truth: (prediction, overlap), ascending
    preds: np.ndarray  # every prediction of the component


def _match_sequentially(component, scores, ignored_gt, ignored_pred, level, compute_fp):
    """The reference compute_statistics loop on one component: (tp, fp, fn, tp scores, the
    matched (ground truth, prediction) pairs)."""
    assigned: set[int] = set()
    tp = fn = 0
    tp_scores, matched = [], []
    for gt, candidates in zip(component.gts, component.candidates, strict=True):
        chosen, best_overlap, chose_ignored = -1, 0.0, False
        best_score = -math.inf
        for pred, overlap in candidates:
            if pred in assigned or (compute_fp and scores[pred] < level):
                continue
            if not compute_fp:
                if scores[pred] > best_score:  # highest score, first on ties
                    chosen, best_score = pred, scores[pred]
            elif ignored_pred[pred] == 0 and (overlap > best_overlap or chose_ignored):
                chosen, best_overlap, chose_ignored = pred, overlap, False
            elif ignored_pred[pred] == 1 and chosen < 0:
                chosen, chose_ignored = pred, True
        if chosen < 0:
            fn += int(ignored_gt[gt] == 0)
            continue
        assigned.add(chosen)
        matched.append((gt, chosen))
        if ignored_gt[gt] == 0 and ignored_pred[chosen] == 0:
            tp += 1
            tp_scores.append(scores[chosen])
    fp = 0
    if compute_fp:
        kept = component.preds[
            (ignored_pred[component.preds] == 0) & (scores[component.preds] >= level)
        ]
        fp = len(kept) - len(assigned.intersection(kept.tolist()))
    return tp, fp, fn, tp_scores, matched


def _components(pred_index, gt_index, overlap, labels) -> list[_Component]:
    order = np.lexsort((pred_index, gt_index, labels))
    pred_index, gt_index, overlap, labels = (
        v[order] for v in (pred_index, gt_index, overlap, labels)
    )
    result = []
    bounds = np.flatnonzero(np.r_[True, labels[1:] != labels[:-1], True])
    for start, stop in zip(bounds[:-1], bounds[1:], strict=True):  # a loop over components
        gts, candidates = [], []
        for k in range(start, stop):
            if not gts or gts[-1] != gt_index[k]:
                gts.append(int(gt_index[k]))
                candidates.append([])
            candidates[-1].append((int(pred_index[k]), float(overlap[k])))
        result.append(_Component(gts, candidates, np.unique(pred_index[start:stop])))
    return result


@dataclass
class _Curve:
    thresholds: np.ndarray  # (T,) descending scores
    tp: np.ndarray  # (T,) counts at each threshold
    fp: np.ndarray
    fn: np.ndarray
    num_gt: int
    totals: dict  # tp, fp, fn with every prediction kept
    tp_heading: np.ndarray | None = None  # (T,) true positives weighted by heading accuracy


def _statistics(
    pred: _Boxes,
    gt: _Boxes,
    pairs: tuple[np.ndarray, np.ndarray],
    overlap: np.ndarray,
    ignored_gt: np.ndarray,
    ignored_pred: np.ndarray,
    min_overlap: float,
    points: int | None = NUM_SAMPLE_POINTS,
    heading: str | None = None,
) -> _Curve:
    """True/false positives and misses at every sampled threshold (`points` of them as the
    reference samples them; None: at every distinct true-positive score), over all frames.
    `heading` ("aos" or "aph", heading.py): also the true positives weighted by how well each
    one's heading matches its ground truth's."""
    pred_index, gt_index = pairs
    keep = (overlap > min_overlap) & (ignored_gt[gt_index] != -1) & (ignored_pred[pred_index] != -1)
    pred_index, gt_index, overlap = pred_index[keep], gt_index[keep], overlap[keep]
    num_gt = int(np.sum(ignored_gt == 0))
    scores = pred.score
    fast, components, in_loop_gt, in_loop_pred = _split_greedy_groups(
        pred_index, gt_index, overlap, len(scores), len(gt.frame)
    )
    pred_index, gt_index, overlap = fast

    # pass 1 (thresholds): each ground truth takes its highest-scoring candidate (first on ties)
    order = np.lexsort((pred_index, -scores[pred_index], gt_index))
    first = order[np.r_[True, gt_index[order][1:] != gt_index[order][:-1]]] if len(order) else order
    is_tp = (ignored_gt[gt_index[first]] == 0) & (ignored_pred[pred_index[first]] == 0)
    tp_scores = [scores[pred_index[first][is_tp]]]
    for component in components:
        tp_scores.append(
            np.asarray(
                _match_sequentially(component, scores, ignored_gt, ignored_pred, 0.0, False)[3]
            )
        )
    tp_scores = np.concatenate(tp_scores)
    thresholds = (
        np.unique(np.asarray(tp_scores, np.float64))[::-1]
        if points is None
        else _sample_thresholds(tp_scores, num_gt, points)
    )
    levels = np.r_[thresholds, -math.inf]  # (T + 1,)

    def weigh(p: np.ndarray, g: np.ndarray) -> np.ndarray:
        return heading_weight(pred.boxes[p, 6], gt.boxes[g, 6], heading or "aos")

    tp, fp, fn, tp_heading = _counts_at_levels(
        (pred_index, gt_index, overlap), scores, ignored_gt, ignored_pred, levels, in_loop_gt,
        in_loop_pred, weigh(pred_index, gt_index) if heading else None,
    )  # fmt: skip
    for component in components:
        for k, level in enumerate(levels):
            part = _match_sequentially(component, scores, ignored_gt, ignored_pred, level, True)
            tp[k] += part[0]
            fp[k] += part[1]
            fn[k] += part[2]
            if heading:
                counted = [
                    (g, p) for g, p in part[4] if ignored_gt[g] == 0 and ignored_pred[p] == 0
                ]
                if counted:
                    g, p = np.asarray(counted).T
                    tp_heading[k] += weigh(p, g).sum()
    return _Curve(
        thresholds=thresholds,
        tp=tp[:-1],
        fp=fp[:-1],
        fn=fn[:-1],
        num_gt=num_gt,
        totals={"tp": int(tp[-1]), "fp": int(fp[-1]), "fn": int(fn[-1])},
        tp_heading=None if tp_heading is None else tp_heading[:-1],
    )


def _split_greedy_groups(
    pred_index: np.ndarray, gt_index: np.ndarray, overlap: np.ndarray, num_pred: int, num_gt: int
):
    """A prediction matching several ground truths makes the greedy order matter: the connected
    groups of boxes around such predictions are matched by the reference loop, the rest at once.
    Returns ((pred_index, gt_index, overlap) of the pairs matched at once, the groups for the
    loop, and which ground truths `(num_gt,)` and predictions `(num_pred,)` the loop owns)."""
    in_loop_gt = np.zeros(num_gt, dtype=bool)
    in_loop_pred = np.zeros(num_pred, dtype=bool)
    slow = np.zeros(len(pred_index), dtype=bool)
    shared = np.bincount(pred_index, minlength=num_pred) > 1
    if shared.any():
        labels = _edge_components(pred_index, gt_index, num_pred, num_gt)
        slow = np.isin(labels, labels[shared[pred_index]])
        in_loop_gt[gt_index[slow]] = True
        in_loop_pred[pred_index[slow]] = True
    components = (
        _components(pred_index[slow], gt_index[slow], overlap[slow], labels[slow])
        if slow.any()
        else []
    )
    fast = (pred_index[~slow], gt_index[~slow], overlap[~slow])
    return fast, components, in_loop_gt, in_loop_pred


def _weighted_at_least(values: np.ndarray, weights: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """Σ weights[values >= level] `(L, K)` for each of `levels (L,)`; values `(N,)`, weights
    `(N, K)` (one sort for all K weightings)."""
    order = np.argsort(values, kind="stable")
    cumulative = np.concatenate([np.zeros((1, weights.shape[1]), weights.dtype),
                                 np.cumsum(weights[order], axis=0)])  # fmt: skip
    below = np.searchsorted(values[order], levels, side="left")
    return cumulative[-1] - cumulative[below]


def _counts_at_levels(
    pairs: tuple[np.ndarray, np.ndarray, np.ndarray],
    scores: np.ndarray,
    ignored_gt: np.ndarray,
    ignored_pred: np.ndarray,
    levels: np.ndarray,
    in_loop_gt: np.ndarray,
    in_loop_pred: np.ndarray,
    pair_weight: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Pass 2: at each score level `(L,)` match the candidate `pairs` (pred, gt, overlap) by
    largest overlap, preferring non-ignored predictions, then the first ignored one; returns
    tp, fp, fn `(L,)` of everything but the loop's groups, and with `pair_weight (E,)` the sum of
    the true positives' weights `(L,)` (else None).

    Per ground truth its candidates are ranked by that preference; at level t it takes the first
    with score >= t. So candidate j is taken exactly for t in (best score of the candidates ranked
    before it, its score] (any t <= its score for the first), an interval, and each count is a
    sum of intervals containing t: O((E + L) log E) instead of one (L, E) pass per level."""
    pred_index, gt_index, overlap = pairs
    pred_ignored = ignored_pred[pred_index]
    rank = np.where(pred_ignored == 0, -overlap, 0.0)
    order = np.lexsort((pred_index, rank, pred_ignored, gt_index))
    pred_sorted, gt_sorted = pred_index[order], gt_index[order]
    edges = len(order)
    first = np.r_[True, gt_sorted[1:] != gt_sorted[:-1]] if edges else np.zeros(0, bool)  # (E,)
    starts = np.flatnonzero(first)
    group_gt = gt_sorted[starts]  # (G,) one group of candidate pairs per ground truth
    score = scores[pred_sorted].astype(np.float64)  # (E,)
    # the best score ranked before each candidate in its group, exactly: a running maximum of
    # (group, score rank) packed into one integer, which no earlier group can exceed
    distinct, score_rank = np.unique(score, return_inverse=True)
    offset = (np.cumsum(first) - 1).astype(np.int64) * max(len(distinct), 1)
    running = np.maximum.accumulate(offset + score_rank) if edges else offset
    before = np.r_[-1, running[:-1]][:edges] - offset  # (E,) rank of the best before; <0: none
    taken = first | (score_rank > before)  # taken at some level
    later = taken & ~first
    lower = distinct[np.maximum(before, 0)] if edges else score  # (E,) the interval's open end
    counted_pred = (ignored_pred[pred_sorted] == 0).astype(np.int64)
    weights = np.c_[counted_pred * (ignored_gt[gt_sorted] == 0), counted_pred]  # (E, 2)
    if pair_weight is not None:  # (E, 3): the true positives' weights as well
        weights = np.c_[weights, weights[:, 0] * np.asarray(pair_weight, np.float64)[order]]
    else:
        weights = weights.astype(np.float64)
    # (L, 2): true positives and matched counted predictions among the candidates taken
    taken_counts = _weighted_at_least(score[taken], weights[taken], levels) - _weighted_at_least(
        lower[later], weights[later], levels
    )
    tp = np.rint(taken_counts[:, 0]).astype(np.int64)
    tp_weighted = taken_counts[:, 2] if pair_weight is not None else None
    best = np.maximum.reduceat(score, starts) if edges else score  # (G,)
    fn = np.searchsorted(np.sort(best[ignored_gt[group_gt] == 0]), levels, side="left")
    has_pair = np.zeros(len(ignored_gt), dtype=bool)
    has_pair[group_gt] = True
    fn = fn + np.sum((ignored_gt == 0) & ~has_pair & ~in_loop_gt)
    eligible = np.sort(scores[(ignored_pred == 0) & ~in_loop_pred])
    kept = len(eligible) - np.searchsorted(eligible, levels, side="left")  # score >= level
    fp = kept - np.rint(taken_counts[:, 1]).astype(np.int64)
    return tp, fp, fn, tp_weighted


def _average_precision(
    curve: _Curve, recall_positions: int, weighted: bool = False
) -> tuple[float | None, dict]:
    """AP in percent (None without counted ground truth) and the interpolated curves.
    `weighted`: the precision's true positives weighted by heading (`curve.tp_heading`): KITTI's
    AOS or the APH, on the same recall grid."""
    if recall_positions == 400:
        return _average_precision_by_recall(curve, recall_positions, weighted)
    precision = np.zeros(NUM_SAMPLE_POINTS)
    recall = np.zeros(NUM_SAMPLE_POINTS)
    count = len(curve.thresholds)
    if count:
        tp = curve.tp.astype(np.float64)
        hits = curve.tp_heading if weighted else tp
        with np.errstate(invalid="ignore", divide="ignore"):
            recall[:count] = np.nan_to_num(tp / (tp + curve.fn))
            precision[:count] = np.nan_to_num(hits / (tp + curve.fp))
    precision = np.maximum.accumulate(precision[::-1])[::-1]
    recall = np.maximum.accumulate(recall[::-1])[::-1]
    if curve.num_gt == 0:
        value = None
    elif recall_positions == 40:
        value = float(precision[1:].sum() / 40 * 100)
    else:
        value = float(precision[::4].sum() / 11 * 100)
    detail = {
        "thresholds": [float(t) for t in curve.thresholds],
        "precision": [float(p) for p in precision],
        "recall": [float(r) for r in recall],
    }
    return value, detail


def _average_precision_by_recall(
    curve: _Curve, positions: int, weighted: bool = False
) -> tuple[float | None, dict]:
    """AP over the recall values k / `positions`, k = 1..positions: at each, the largest precision
    at any threshold whose recall reaches it (0 where none does), from a curve thresholded at
    every true-positive score. Curves: "precision" and "recall" at k = 0..positions (recall k /
    positions where reached, else 0)."""
    grid = np.arange(positions + 1) / positions  # (P + 1,)
    precision = np.zeros(positions + 1)
    if len(curve.thresholds) and curve.num_gt:
        tp = curve.tp.astype(np.float64)
        recall = tp / curve.num_gt  # (T,) non-decreasing: thresholds fall
        hits = curve.tp_heading if weighted else tp
        with np.errstate(invalid="ignore", divide="ignore"):
            at = np.nan_to_num(hits / (tp + curve.fp))
        envelope = np.maximum.accumulate(at[::-1])[::-1]  # best precision at recall >= recall[t]
        first = np.searchsorted(recall, grid - 1e-12, side="left")  # first threshold reaching it
        reached = first < len(recall)
        precision[reached] = envelope[first[reached]]
    value = None if curve.num_gt == 0 else float(precision[1:].sum() / positions * 100)
    detail = {
        "thresholds": [float(t) for t in curve.thresholds],
        "precision": [float(p) for p in precision],
        "recall": [float(r) if p > 0 else 0.0 for r, p in zip(grid, precision, strict=True)],
    }
    return value, detail


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
            if metric == "bev":  # the heading metrics on the BEV matches (docs/evaluation.md)
                result["aos"][name] = _average_precision(curve, recall_positions, True)[0]
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


def format_table(metrics: dict) -> str:
    """A plain-text table: AP_BEV / AP_3D per difficulty or band, with the match counts."""
    lines = []
    for class_name, result in metrics.items():
        lines.append(
            f"{class_name} AP_R{result['recall_positions']} @ IoU {result['iou']:g} "
            f"(protocol {result['protocol']}, {result['frames']} frames)"
        )
        header = f"{'':<10}{'AP_BEV':>8}{'AP_3D':>8}{'APH':>8}{'AOS':>8}{'GT':>8}{'ign':>6}"
        header += f"{'pred':>8}{'TP/FP/FN (BEV)':>22}{'TP/FP/FN (3D)':>22}{'backwards':>12}"
        lines.append(header)
        for name in result["bev"]:
            counts = result["counts"][name]
            headings = (result.get("aph", {}).get(name), result.get("aos", {}).get(name))

            def show(value):
                return f"{value:8.2f}" if value is not None else f"{'-':>8}"

            row = f"{name:<10}{show(result['bev'][name])}{show(result['3d'][name])}"
            row += f"{show(headings[0])}{show(headings[1])}"
            row += f"{counts['gt']:>8}{counts['gt_ignored']:>6}{counts['pred']:>8}"
            for metric in ("bev", "3d"):
                totals = counts[metric]
                row += f"{totals['tp']:>10}/{totals['fp']}/{totals['fn']}".rjust(22)
            heading = result.get("heading", {}).get(name)
            if heading and heading["tp"]:
                row += f"{heading['backwards']}/{heading['tp']}".rjust(12)
            lines.append(row)
        lines.append(
            "APH, AOS: AP_BEV with each true positive weighted by its heading (Waymo's "
            "1 - |dθ|/π, KITTI's (1 + cos dθ)/2); backwards: true positives facing > 90° away"
        )
        lines.extend(ceiling_notes(result))
    return "\n".join(lines)


def ceiling_notes(result: dict) -> list[str]:
    """One line per group whose AP cannot reach 100 with so few counted ground truths (a
    class's `evaluate` result; none when every group can, or under R400)."""
    notes = []
    for name, counts in result["counts"].items():
        ceiling = counts.get("ap_ceiling")
        if ceiling is not None and ceiling < 100.0:
            notes.append(
                f"{name}: only {counts['gt']} ground truths count: a perfect detector scores "
                f"{ceiling:.2f} under R{result['recall_positions']} (the KITTI reference samples "
                f"one threshold per true positive below 41); --recall-positions 400 reads the "
                f"precision at exact recalls"
            )
    return notes


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
