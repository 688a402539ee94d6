"""The matching behind KITTI-protocol AP: true and false positives and misses at every score
threshold (vectorized over frames, the reference loop on the rare groups where one prediction
overlaps several labels), the precision-recall curve and its AP (R40, R11, R400), and the same
curve with each true positive weighted by its heading (AOS, APH). evaluate.py owns the inputs,
ignore rules and the public API; this module the counting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dali_cli.evaluation.heading import heading_weight

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
    pred,  # evaluate._Boxes: the predictions (score, boxes), in the evaluator's order
    gt,  # evaluate._Boxes: the ground truth
    pairs: tuple[np.ndarray, np.ndarray],
    overlap: np.ndarray,
    ignored_gt: np.ndarray,
    ignored_pred: np.ndarray,
    min_overlap: float,
    points: int | None = NUM_SAMPLE_POINTS,
    heading: str | None = None,
    yaw: tuple[np.ndarray, np.ndarray] | None = None,
) -> _Curve:
    """True/false positives and misses at every sampled threshold (`points` of them as the
    reference samples them; None: at every distinct true-positive score), over all frames.
    `heading` ("aos" or "aph", heading.py): also the true positives weighted by how well each
    one's heading matches its ground truth's: their yaws, or the angles `yaw` `((P,), (G,))`
    (KITTI's AOS on image boxes weighs the observation angles alpha)."""
    pred_yaw, gt_yaw = yaw if yaw is not None else (pred.boxes[:, 6], gt.boxes[:, 6])
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
        return heading_weight(pred_yaw[p], gt_yaw[g], heading or "aos")

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
