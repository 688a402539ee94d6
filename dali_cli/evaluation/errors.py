"""Why AP is what it is: the error of every matched box and a TIDE-style split of the false ones.

Box errors: for the true positives at IoU 0.5 (BEV), prediction minus ground truth along the range
direction (sensor → ground-truth centre in BEV), across it, in z, l, w, h and yaw, summarized
overall and per range band. False positives: background, mislocalized or duplicate, per IoU
threshold and overlap kind, with the AP each kind costs (TIDE's dAP: AP with that kind fixed minus
AP). The matching is the evaluator's own (`evaluate.matched_ground_truth`), so the true and false
positives are those `counts` reports and AP scores. Definitions: docs/evaluation.md.
"""

from __future__ import annotations

import math

import numpy as np

from dali_cli import geometry
from dali_cli.evaluation.evaluate import (
    Scored,
    average_precision,
    matched_ground_truth,
    scored_boxes,
)
from dali_cli.store.artifacts import BOX_FIELDS, BoxTable

# range bands of the box-error summary (BEV distance of the ground-truth centre, metres)
ERROR_BANDS_M = {"all": (0.0, math.inf), "0-20": (0.0, 20.0), "20-40": (20.0, 40.0),
                 "40+": (40.0, math.inf)}  # fmt: skip
TP_IOU = 0.5  # true positives whose errors are summarized: BEV IoU above this
TP_OVERLAP = "bev"  # BEV matching keeps boxes with a poor z or h, so their errors show
BACKGROUND_IOU = 0.1  # a false positive overlapping no ground truth by this much is background
QUANTITIES = ("radial_m", "tangential_m", "z_m", "l_m", "w_m", "h_m", "yaw_axis_deg")
KINDS = ("background", "mislocalized", "duplicate")  # false-positive kinds, codes 1, 2, 3
FIXES = ("mislocalized", "duplicate", "background", "missed")  # what dAP fixes, one at a time


def box_errors(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Errors `(n, 7)` float64 of predicted boxes `pred (n, 7)` against their ground truths
    `gt (n, 7)` (x, y, z, l, w, h, yaw; metres, radians), columns QUANTITIES:

    - radial_m: the BEV centre offset along the unit vector from the sensor (the origin) to the
      ground-truth centre; positive = the box lies too far from the sensor;
    - tangential_m: the offset across it, positive counter-clockwise (towards +yaw of the ray);
    - z_m, l_m, w_m, h_m: prediction minus ground truth;
    - yaw_axis_deg: the error of the box's heading axis, the wrapped difference modulo 180 deg in
      [-90, 90): what the overlap sees. A box turned by 180 deg overlaps as well as the right one
      and has an axis error near 0; `turned_around` tells it apart.

    A ground truth at the sensor's own position (range 0) takes the +x axis as its ray."""
    pred = np.asarray(pred, dtype=np.float64).reshape(-1, 7)
    gt = np.asarray(gt, dtype=np.float64).reshape(-1, 7)
    distance = np.hypot(gt[:, 0], gt[:, 1])  # (n,)
    at_origin = distance == 0
    scale = np.where(at_origin, 1.0, distance)[:, None]  # (n, 1)
    ray = np.where(at_origin[:, None], [1.0, 0.0], gt[:, :2] / scale)  # (n, 2) unit vectors
    offset = pred[:, :2] - gt[:, :2]  # (n, 2)
    radial = np.sum(offset * ray, axis=1)
    tangential = ray[:, 0] * offset[:, 1] - ray[:, 1] * offset[:, 0]
    axis = np.degrees(geometry.wrap_angle(2 * (pred[:, 6] - gt[:, 6]))) / 2  # [-90, 90)
    return np.column_stack([radial, tangential, pred[:, 2:6] - gt[:, 2:6], axis])  # (n, 7)


def turned_around(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """`(n,)` bool: the predicted heading `pred (n, 7)` points more than 90 deg away from the
    ground truth's `gt (n, 7)` (the box faces backwards; its axis may still be right)."""
    pred = np.asarray(pred, dtype=np.float64).reshape(-1, 7)
    gt = np.asarray(gt, dtype=np.float64).reshape(-1, 7)
    return np.abs(geometry.wrap_angle(pred[:, 6] - gt[:, 6])) > np.pi / 2


def summarize(values: np.ndarray) -> dict:
    """median, mean (the bias), median_abs and the 16 / 84 % percentiles of `values (n,)`
    (None each for n = 0)."""
    values = np.asarray(values, dtype=np.float64)
    if len(values) == 0:
        return dict.fromkeys(("median", "mean", "median_abs", "p16", "p84"))
    p16, median, p84 = np.percentile(values, [16, 50, 84])
    return {
        "median": round(float(median), 4),
        "mean": round(float(values.mean()), 4),
        "median_abs": round(float(np.median(np.abs(values))), 4),
        "p16": round(float(p16), 4),
        "p84": round(float(p84), 4),
    }


SIZE_SPREAD = (("l_m", 3), ("w_m", 4))  # the sizes whose spread is compared, (name, box column)


def size_spread(predicted: np.ndarray, truth: np.ndarray) -> dict:
    """How much the true positives' sizes vary, predicted against labelled: per SIZE_SPREAD
    column of the matched `predicted (n, 7)` and `truth (n, 7)` boxes, the 5 / 95 % percentiles
    and the standard deviation (m) of each, and `spread_ratio`, the predicted 5-95 % range over
    the labels' (1: as varied as the cars; near 0: every car the same size). None each for n < 2."""
    result = {}
    for name, column in SIZE_SPREAD:
        block = {}
        for side, boxes in (("predicted", predicted), ("labels", truth)):
            values = np.asarray(boxes[:, column], np.float64)
            if len(values) < 2:
                block[side] = dict.fromkeys(("p5", "p95", "std"))
                continue
            p5, p95 = np.percentile(values, [5, 95])
            block[side] = {"p5": round(float(p5), 4), "p95": round(float(p95), 4),
                           "std": round(float(values.std()), 4)}  # fmt: skip
        ranges = [block[side]["p95"] - block[side]["p5"] if block[side]["p5"] is not None else None
                  for side in ("predicted", "labels")]  # fmt: skip
        ratio = ranges[0] / ranges[1] if ranges[1] else None  # no spread in the labels: no ratio
        block["spread_ratio"] = None if ratio is None else round(float(ratio), 4)
        result[name] = block
    return result


def errors_by_band(
    errors: np.ndarray, distance_m: np.ndarray, turned: np.ndarray, bands: dict = ERROR_BANDS_M
) -> dict:
    """Per band of `bands` (name -> [low, high) metres of `distance_m (n,)`): the count, the boxes
    facing backwards ("flipped": `turned (n,)` bool, `turned_around`) and `summarize` of each
    column of `errors (n, 7)`."""
    summary = {}
    for name, (low, high) in bands.items():
        inside = (distance_m >= low) & (distance_m < high)
        block = {"count": int(inside.sum()), "flipped": int(np.sum(turned[inside]))}
        for column, quantity in enumerate(QUANTITIES):
            block[quantity] = summarize(errors[inside, column])
        summary[name] = block
    return summary


def best_overlaps(
    pairs: tuple[np.ndarray, np.ndarray], overlap: np.ndarray, count: int, valid: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """For each of `count` boxes on the pairs' first side: its largest `overlap (E,)` with a box
    of the second side marked `valid` (bool, by index), and that box's index (-1, overlap 0 when
    none). `pairs`: (first (E,), second (E,)) indices."""
    first, second = pairs
    keep = valid[second]
    first, second, overlap = first[keep], second[keep], overlap[keep]
    order = np.lexsort((second, -overlap, first))  # per box: largest overlap first
    head = order[np.r_[True, first[order][1:] != first[order][:-1]]] if len(order) else order
    best = np.zeros(count)
    partner = np.full(count, -1, dtype=np.int64)
    best[first[head]] = overlap[head]
    partner[first[head]] = second[head]
    return best, partner


def false_positive_kinds(
    is_fp: np.ndarray, best_iou: np.ndarray, iou: float, background_iou: float = BACKGROUND_IOU
) -> np.ndarray:
    """`(P,)` int8 kind of each prediction: 0 not a false positive, else 1 + the index in KINDS:
    background (largest IoU with any ground truth of the class < `background_iou`), mislocalized
    (`background_iou` <= it <= `iou`: would match if better placed) or duplicate (> `iou`: the
    ground truth it overlaps was matched to another prediction). `is_fp`, `best_iou`: `(P,)`."""
    kind = np.where(best_iou < background_iou, 1, np.where(best_iou <= iou, 2, 3))
    return np.where(is_fp, kind, 0).astype(np.int8)


def _tables_fixed(scored: Scored, kind, matched, partner, missed) -> dict[str, tuple]:
    """(predictions, ground truth) tables with one kind of error fixed, per FIXES entry: each
    mislocalized false positive takes the box of the ground truth it overlaps most (removed
    instead when that ground truth is matched already or a higher-scored one takes it); the
    duplicates or the background false positives removed; the missed ground truths removed."""
    pred, gt = scored.pred_table, scored.gt_table
    rows = scored.pred.row  # (P,) table row of each prediction
    keep_all = np.ones(len(pred), dtype=bool)
    fixed = {}
    for code, name in enumerate(KINDS, start=1):
        if name == "mislocalized":
            continue
        keep = keep_all.copy()
        keep[rows[kind == code]] = False
        fixed[name] = (pred.select(keep), gt)
    # mislocalized: the highest-scored box per free ground truth snaps to it, the others go
    loose = np.flatnonzero(kind == 2)
    taken = np.zeros(len(scored.gt.frame), dtype=bool)
    taken[matched[matched >= 0]] = True
    order = loose[np.lexsort((loose, -scored.pred.score[loose], partner[loose]))]
    target = partner[order]
    leader = np.r_[True, target[1:] != target[:-1]] if len(order) else np.zeros(0, bool)
    snap = order[leader & ~taken[target]]
    keep = keep_all.copy()
    keep[rows[np.setdiff1d(loose, snap)]] = False
    boxes = pred.boxes.copy()
    boxes[rows[snap]] = scored.gt.boxes[partner[snap]]
    snapped = pred.with_columns(**{name: boxes[:, i] for i, name in enumerate(BOX_FIELDS)})
    fixed["mislocalized"] = (snapped.select(keep), gt)
    keep_gt = np.ones(len(gt), dtype=bool)
    keep_gt[scored.gt.row[missed]] = False
    fixed["missed"] = (pred, gt.select(keep_gt))
    return {name: fixed[name] for name in FIXES}


def breakdown(
    pred: BoxTable,
    gt: BoxTable,
    ious: tuple[float, ...] = (0.7,),
    recall_positions: int = 40,
    protocol: str = "auto",
    class_name: str = "Car",
    min_gt_points: int = 0,
    frame_ids: list[str] | None = None,
    front_only: bool = False,
    scored: Scored | None = None,
) -> dict:
    """The error breakdown of `pred` against `gt` under the same protocol as `evaluate` (same
    arguments): box errors of the true positives at TP_IOU in the headline group (KITTI moderate,
    or "all" of the range bands); per threshold in `ious` and overlap kind, the false positives
    of every group split into KINDS with the misses, and the headline group's AP with each of
    FIXES applied alone. A JSON-ready dict (docs/evaluation.md, "Error breakdown"). `scored`:
    `scored_boxes` of the same arguments when the caller has it."""
    if scored is None:
        scored = scored_boxes(
            pred, gt, protocol, class_name, min_gt_points, frame_ids, front_only
        )  # fmt: skip
    group = next(key for key in ("moderate", "all", *scored.flags) if key in scored.flags)
    ignored_gt, ignored_pred = scored.flags[group]
    matched = matched_ground_truth(scored, TP_OVERLAP, group, TP_IOU)
    true = (matched >= 0) & (ignored_pred == 0)
    true[true] = ignored_gt[matched[true]] == 0
    truth = scored.gt.boxes[matched[true]]  # (n, 7)
    predicted = scored.pred.boxes[true]  # (n, 7)
    errors = box_errors(predicted, truth)
    result = {
        "class": class_name,
        "protocol": scored.protocol,
        "group": group,
        "background_iou": BACKGROUND_IOU,
        "true_positives": {
            "iou": TP_IOU,
            "overlap": TP_OVERLAP,
            "bands_m": {
                name: [low, None if math.isinf(high) else high]
                for name, (low, high) in ERROR_BANDS_M.items()
            },
            **errors_by_band(
                errors, np.hypot(truth[:, 0], truth[:, 1]), turned_around(predicted, truth)
            ),
            "sizes": size_spread(predicted, truth),
        },
        "false_positives": {},
    }
    options = dict(
        protocol=scored.protocol, class_name=class_name, min_gt_points=min_gt_points,
        frame_ids=list(scored.frame_ids), front_only=front_only,
    )  # fmt: skip
    for iou in ious:
        block = {}
        for metric in ("bev", "3d"):
            splits = {name: _split(scored, metric, name, iou) for name in scored.flags}
            fixed = _tables_fixed(scored, *splits[group][1:])
            block[metric] = {
                "counts": {name: split[0] for name, split in splits.items()},
                "ap": average_precision(scored, metric, group, iou, recall_positions),
                "ap_fixed": {
                    name: average_precision(
                        scored_boxes(p, g, **options), metric, group, iou, recall_positions
                    )
                    for name, (p, g) in fixed.items()
                },
            }
        result["false_positives"][f"{iou:g}"] = block
    return result


def _split(scored: Scored, metric: str, group: str, iou: float):
    """(counts, kind (P,), matched (P,), best ground truth of each prediction (P,), missed ground
    truths (G,) bool) of one group at one threshold."""
    ignored_gt, ignored_pred = scored.flags[group]
    matched = matched_ground_truth(scored, metric, group, iou)
    overlap = scored.overlap[metric]
    best, partner = best_overlaps(scored.pairs, overlap, len(matched), ignored_gt != -1)
    is_fp = (ignored_pred == 0) & (matched < 0)
    kind = false_positive_kinds(is_fp, best, iou)
    # misses no prediction of the class came near: counted, unmatched, best IoU < BACKGROUND_IOU
    reverse = (scored.pairs[1], scored.pairs[0])
    near, _ = best_overlaps(reverse, overlap, len(ignored_gt), ignored_pred != -1)
    unmatched = np.ones(len(ignored_gt), dtype=bool)
    unmatched[matched[matched >= 0]] = False
    missed = (ignored_gt == 0) & unmatched & (near < BACKGROUND_IOU)
    true = (matched >= 0) & (ignored_pred == 0)
    true[true] = ignored_gt[matched[true]] == 0
    counts = {
        "tp": int(true.sum()),
        "fp": int(is_fp.sum()),
        "fn": int(np.sum((ignored_gt == 0) & unmatched)),
        **{name: int(np.sum(kind == code)) for code, name in enumerate(KINDS, start=1)},
        "missed": int(missed.sum()),
    }
    return counts, kind, matched, partner, missed


def largest_loss(block: dict) -> tuple[str, float] | None:
    """(fix, AP gained) of the fix that gains most in one `false_positives[iou][metric]` block,
    None without AP."""
    base = block.get("ap")
    gains = {k: v - base for k, v in block.get("ap_fixed", {}).items() if v is not None}
    if base is None or not gains:
        return None
    name = max(gains, key=gains.get)
    return name, gains[name]


def format_breakdown(result: dict) -> str:
    """Plain-text summary for `dali eval`: box errors (all ranges) and the false positives with
    the AP each fix gains, per threshold, in the headline group. A quantity an older breakdown
    lacks is left out."""
    tps = result["true_positives"]
    group = result["group"]
    lines = [
        f"Error breakdown ({result['protocol']} {group}): {tps['all']['count']} true positives "
        f"at {tps['overlap'].upper()} IoU > {tps['iou']:g} ({tps['all']['flipped']} facing "
        "backwards), prediction - truth",
        f"{'':<14}{'median':>9}{'bias':>9}{'med|e|':>9}{'16%':>9}{'84%':>9}",
    ]
    for quantity in QUANTITIES:
        stats = tps["all"].get(quantity)
        if stats is None:
            continue
        cells = "".join(
            f"{stats[k]:9.3f}" if stats[k] is not None else f"{'-':>9}"
            for k in ("median", "mean", "median_abs", "p16", "p84")
        )
        lines.append(f"{quantity:<14}{cells}")
    for name, block in (tps.get("sizes") or {}).items():
        predicted, labels = block["predicted"], block["labels"]
        if predicted["p5"] is None:
            continue
        lines.append(
            f"{name[0]} spread: predicted {predicted['p5']:.2f}-{predicted['p95']:.2f} m, labels "
            f"{labels['p5']:.2f}-{labels['p95']:.2f} m (5-95 %), ratio "
            + ("-" if block["spread_ratio"] is None else f"{block['spread_ratio']:.2f}")
        )
    lines.append(
        f"{'IoU':<10}{'TP':>6}{'FP':>6}{'bg':>6}{'misloc':>7}{'dup':>6}{'missed':>7}"
        f"{'AP':>8}  AP if fixed: " + " / ".join(FIXES)
    )
    for iou, block in result["false_positives"].items():
        for metric, entry in block.items():
            counts = entry["counts"][group]
            fixed = " / ".join(
                f"{entry['ap_fixed'][name]:.1f}" if entry["ap_fixed"][name] is not None else "-"
                for name in FIXES
            )
            ap = entry["ap"]
            lines.append(
                f"{metric + '@' + iou:<10}{counts['tp']:>6}{counts['fp']:>6}"
                f"{counts['background']:>6}{counts['mislocalized']:>7}{counts['duplicate']:>6}"
                f"{counts['missed']:>7}{(f'{ap:.2f}' if ap is not None else '-'):>8}  {fixed}"
            )
    return "\n".join(lines)
