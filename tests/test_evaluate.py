"""KITTI-protocol AP: hand-computed cases, an independent port of the reference loop on random
scenes, ignore rules, label_2 equivalence and the `dali eval` command."""

from __future__ import annotations

import json
import math
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from kitti_reference import reference_statistics, reference_thresholds

from dali_cli import geometry
from dali_cli.cli import main
from dali_cli.evaluation.evaluate import (
    DIFFICULTIES,
    RANGE_BANDS_M,
    EvaluationError,
    ap_ceiling,
    evaluate,
    format_table,
)
from dali_cli.importers.kitti_label import read_label_dir, read_label_file, write_label_dir
from dali_cli.store.artifacts import BoxTable, read_boxes, write_boxes, write_frameset

CAR = (3.9, 1.6, 1.5)


def row_of_cars(count: int, spacing: float = 8.0) -> np.ndarray:
    """`count` separated cars `(count, 7)` along +x, 5 m to the side."""
    x = 5.0 + spacing * np.arange(count)
    return np.c_[
        x, np.full(count, 5.0), np.full(count, -0.9), np.tile(CAR, (count, 1)), np.zeros(count)
    ]


def table(boxes, frame="000000", score=None, label="Car", **extra) -> BoxTable:
    boxes = np.asarray(boxes, float).reshape(-1, 7)
    return BoxTable.from_arrays([frame] * len(boxes), boxes, score=score, label=label, **extra)


def kitti_columns(count, height=100.0, occluded=0, truncated=0.0):
    return {
        "truncated": np.full(count, truncated, np.float32),
        "occluded": np.full(count, occluded, np.int32),
        "alpha": np.zeros(count),
        "bbox_left": np.zeros(count, np.float32),
        "bbox_top": np.zeros(count, np.float32),
        "bbox_right": np.full(count, 50.0, np.float32),
        "bbox_bottom": np.full(count, height, np.float32),
    }


# ---------------------------------------------------------------------------------------------
# Hand-computed cases


@pytest.mark.parametrize("count, expected", [(50, 100.0), (41, 100.0), (20, 100 * 19 / 40)])
def test_perfect_predictions(count, expected):
    cars = row_of_cars(count)
    scores = np.linspace(0.9, 0.5, count)
    metrics = evaluate(table(cars, score=scores), table(cars))["Car"]
    assert metrics["protocol"] == "range"
    assert metrics["bev"]["all"] == pytest.approx(expected)
    assert metrics["3d"]["all"] == pytest.approx(expected)
    assert metrics["counts"]["all"]["bev"] == {"tp": count, "fp": 0, "fn": 0}
    r11 = evaluate(table(cars, score=scores), table(cars), recall_positions=11)["Car"]
    assert r11["bev"]["all"] == pytest.approx(100.0 if count >= 41 else 100 * 5 / 11)


@pytest.mark.parametrize("count", [1, 9, 20, 22, 39, 40, 41, 60])
@pytest.mark.parametrize("positions", [40, 11, 400])
def test_the_ceiling_is_what_a_perfect_detector_scores(count, positions):
    """ap_ceiling is a perfect detector's AP with that many counted cars (computed apart, with no
    evaluation), and the table says so wherever it is below 100."""
    cars = row_of_cars(count)
    scores = np.linspace(0.9, 0.5, count)
    metrics = evaluate(table(cars, score=scores), table(cars), recall_positions=positions)["Car"]
    ceiling = metrics["counts"]["all"]["ap_ceiling"]
    assert ceiling == pytest.approx(metrics["bev"]["all"])
    assert ceiling == ap_ceiling(count, positions)
    assert (ceiling < 100.0) == (positions != 400 and count < 41)
    assert ("only 22 ground truths count" in format_table({"Car": metrics})) == (
        count == 22 and positions != 400
    )


def test_the_ceiling_of_no_ground_truth_is_none():
    assert ap_ceiling(0) is None


def test_all_false_predictions_give_zero():
    cars = row_of_cars(45)
    wrong = cars + [0, 4.0, 0, 0, 0, 0, 0]  # 4 m to the side: no overlap
    metrics = evaluate(table(wrong, score=np.full(45, 0.9)), table(cars))["Car"]
    assert metrics["bev"]["all"] == 0.0 and metrics["3d"]["all"] == 0.0
    assert metrics["counts"]["all"]["bev"] == {"tp": 0, "fp": 45, "fn": 45}


def known_curve_scene():
    """40 cars all found (scores 1.0 .. 0.61) and 10 false positives scored between the 20th
    and the 21st true positive: precision 1 up to recall 20/40, then (k + 1) / (k + 11)."""
    cars = row_of_cars(40)
    tp_scores = 1.0 - 0.01 * np.arange(40)
    false = row_of_cars(10) + [0, 30.0, 0, 0, 0, 0, 0]
    pred = np.r_[cars, false]
    scores = np.r_[tp_scores, np.full(10, 0.805)]
    return pred, scores, cars


def test_known_precision_recall_curve():
    pred, scores, cars = known_curve_scene()
    # interpolated precision: 1 at entries 0..19, max((k+1)/(k+11)) = 40/50 at 20..39, 0 at 40
    r40 = (19 * 1.0 + 20 * 0.8) / 40 * 100
    r11 = (5 * 1.0 + 5 * 0.8) / 11 * 100
    metrics = evaluate(table(pred, score=scores), table(cars))["Car"]
    assert metrics["bev"]["all"] == pytest.approx(r40)
    assert metrics["3d"]["all"] == pytest.approx(r40)
    curve = metrics["curves"]["bev"]["all"]
    assert len(curve["thresholds"]) == 40
    assert curve["precision"][19] == 1.0 and curve["precision"][20] == pytest.approx(0.8)
    assert evaluate(table(pred, score=scores), table(cars), recall_positions=11)["Car"]["bev"][
        "all"
    ] == pytest.approx(r11)


def test_thresholds_with_more_than_41_ground_truths():
    # the minimal case of more than 41 ground truths: 50 counted cars on a 10 x 5 grid, the first 9 found with scores
    # 0.9 .. 0.1. Recall reaches 9/50 = 0.18: R40 positions 1/40 .. 7/40 have precision 1, which
    # OpenPCDet's get_thresholds (next recall (i + 2) / num_gt) gives; (i + 3) / num_gt gave 20.0.
    x, y = np.meshgrid(5.0 + 5.0 * np.arange(10), -16.0 + 8.0 * np.arange(5))
    count = x.size
    cars = np.c_[
        x.ravel(), y.ravel(), np.full(count, -0.9), np.tile(CAR, (count, 1)), np.zeros(count)
    ]
    gt = table(cars, **kitti_columns(count, height=75.0))
    found = cars[:9]
    pred = table(found, score=np.round(0.9 - 0.1 * np.arange(9), 1), **kitti_columns(9, 75.0))
    metrics = evaluate(pred, gt, protocol="kitti")["Car"]
    for metric in ("bev", "3d"):
        for level in ("easy", "moderate", "hard"):
            assert metrics[metric][level] == pytest.approx(17.5), (metric, level)
    expected = reference_thresholds(list(pred["score"].astype(float)), count)
    assert metrics["curves"]["bev"]["moderate"]["thresholds"] == pytest.approx(expected)


def test_overlap_test_is_strict():
    gt = np.array([[10.0, 0, 0, 3.0, 2.0, 1.5, 0.0]] * 1)
    pred = gt + [1.0, 0, 0, 0, 0, 0, 0]  # BEV overlap 2 x 2 over union 8: IoU exactly 0.5
    assert geometry.bev_iou(pred, gt)[0, 0] == 0.5
    at = evaluate(table(pred), table(gt), iou=0.5)["Car"]["counts"]["all"]["bev"]
    below = evaluate(table(pred), table(gt), iou=0.49)["Car"]["counts"]["all"]["bev"]
    assert at == {"tp": 0, "fp": 1, "fn": 1}
    assert below == {"tp": 1, "fp": 0, "fn": 0}


def test_ignored_ground_truth_changes_nothing():
    pred, scores, cars = known_curve_scene()
    base = evaluate(
        table(pred, score=scores), table(cars, **kitti_columns(len(cars))), protocol="kitti"
    )["Car"]
    vans = row_of_cars(6) + [0, -20.0, 0, 0, 0, 0, 0]  # 3 detected, 3 missed
    hard_cars = row_of_cars(4) + [0, -40.0, 0, 0, 0, 0, 0]  # occluded: not easy, detected
    small_cars = row_of_cars(3) + [0, -60.0, 0, 0, 0, 0, 0]  # 2D height 30 px: not easy
    dont_care = row_of_cars(2) + [0, 60.0, 0, 0, 0, 0, 0]
    gt = BoxTable.concat(
        [
            table(cars, **kitti_columns(len(cars))),
            table(vans, label="Van", **kitti_columns(6)),
            table(hard_cars, **kitti_columns(4, occluded=2)),
            table(small_cars, **kitti_columns(3, height=30.0)),
            table(dont_care, label="DontCare", **kitti_columns(2)),
        ]
    )
    extra_pred = np.r_[vans[:3], hard_cars, small_cars, dont_care[:0]]
    all_pred = np.r_[pred, extra_pred]
    all_scores = np.r_[scores, np.full(len(extra_pred), 0.95)]
    metrics = evaluate(table(all_pred, score=all_scores), gt, protocol="kitti")["Car"]
    assert metrics["bev"]["easy"] == pytest.approx(base["bev"]["easy"])
    assert metrics["3d"]["easy"] == pytest.approx(base["3d"]["easy"])
    assert metrics["counts"]["easy"]["gt"] == 40
    assert metrics["counts"]["easy"]["gt_ignored"] == 6 + 4 + 3
    # moderate admits 2D boxes of 30 px; occlusion 2 is admitted by hard only
    assert metrics["counts"]["moderate"]["gt"] == 43
    assert metrics["counts"]["hard"]["gt"] == 47


def test_other_classes_do_not_absorb_detections():
    cars = row_of_cars(45)
    trucks = row_of_cars(5) + [0, 20.0, 0, 0, 0, 0, 0]
    gt = BoxTable.concat([table(cars), table(trucks, label="Truck")])
    pred = table(np.r_[cars, trucks], score=np.r_[np.full(45, 0.5), np.full(5, 0.9)])
    counts = evaluate(pred, gt)["Car"]["counts"]["all"]["bev"]
    assert counts == {"tp": 45, "fp": 5, "fn": 0}
    # the same boxes labelled Van are ignored instead: no false positives
    gt_van = BoxTable.concat([table(cars), table(trucks, label="Van")])
    assert evaluate(pred, gt_van)["Car"]["counts"]["all"]["bev"] == {"tp": 45, "fp": 0, "fn": 0}


def test_range_bands_separate_by_distance():
    near = row_of_cars(1)  # one car at x = 5 in each of 45 frames
    far = near + [40.0, 0, 0, 0, 0, 0, 0]  # at about 45 m
    gt = BoxTable.concat(
        [table(near, frame=f"{k:03d}") for k in range(45)] + [table(far, frame="far")]
    )
    pred = BoxTable.concat(
        [table(near, frame=f"{k:03d}") for k in range(45)]
        + [table(far + [0, 3.0, 0, 0, 0, 0, 0], frame="far", score=[0.99])]  # misses the far car
    )
    metrics = evaluate(pred, gt)["Car"]
    assert metrics["counts"]["0-30"] == {
        "gt": 45,
        "gt_ignored": 1,
        "pred": 45,
        "bev": {"tp": 45, "fp": 0, "fn": 0},
        "3d": {"tp": 45, "fp": 0, "fn": 0},
        "ap_ceiling": 100.0,
    }
    assert metrics["bev"]["0-30"] == pytest.approx(100.0)
    assert metrics["counts"]["30-50"]["bev"] == {"tp": 0, "fp": 1, "fn": 1}
    assert metrics["bev"]["50-80"] is None  # no ground truth in the band
    assert metrics["counts"]["all"]["bev"] == {"tp": 45, "fp": 1, "fn": 1}


def test_st3d_protocol_filters_the_field_of_view():
    x, y = np.meshgrid(12.0 + 6 * np.arange(9), [-8.0, -4.0, 0.0, 4.0, 8.0])
    front = np.c_[x.ravel(), y.ravel(), np.full(45, -0.9), np.tile(CAR, (45, 1)), np.zeros(45)]
    behind = front[:5] * [-1, 1, 1, 1, 1, 1, 1]
    gt = BoxTable.concat([table(front), table(behind)])
    pred = table(np.r_[front, behind], score=np.r_[np.full(45, 0.5), np.full(5, 0.9)])
    metrics = evaluate(pred, gt, protocol="st3d")["Car"]
    assert metrics["bev"]["easy"] == metrics["bev"]["moderate"] == metrics["bev"]["hard"]
    assert metrics["counts"]["easy"]["gt"] == 45
    assert metrics["counts"]["easy"]["bev"] == {"tp": 45, "fp": 5, "fn": 0}
    # with FOV-cropped predictions (as from KITTI's FOV-only clouds) the 5 behind are gone
    cropped = evaluate(pred, gt, protocol="st3d", front_only=True)["Car"]
    assert cropped["counts"]["easy"]["pred"] == 45
    assert cropped["counts"]["easy"]["bev"] == {"tp": 45, "fp": 0, "fn": 0}
    assert cropped["bev"]["easy"] > metrics["bev"]["easy"]
    # range bands of the front region: the 5 cars behind take no part at all
    front = evaluate(pred, gt, protocol="range", front_only=True)["Car"]
    assert front["counts"]["all"]["gt"] == 45 and front["counts"]["all"]["pred"] == 45
    assert front["bev"]["all"] == cropped["bev"]["easy"]
    assert front["counts"]["0-30"]["gt"] == 15  # x = 12, 18, 24 m (5 each, all within 25.3 m)


def test_min_gt_points_ignores_instead_of_dropping():
    cars = row_of_cars(45)
    points = np.r_[np.full(40, 50), np.full(5, 2)]
    gt = table(cars, num_points=points)
    pred = table(cars[:40], score=np.full(40, 0.5))  # the 5 sparse cars are not detected
    strict = evaluate(pred, gt, min_gt_points=5)["Car"]
    assert strict["counts"]["all"]["gt"] == 40 and strict["counts"]["all"]["gt_ignored"] == 5
    assert strict["bev"]["all"] == pytest.approx(100.0 * 39 / 40)
    # a detection of a sparse car is not a false positive either
    found = evaluate(table(cars, score=np.full(45, 0.5)), gt, min_gt_points=5)["Car"]
    assert found["counts"]["all"]["bev"] == {"tp": 40, "fp": 0, "fn": 0}
    with pytest.raises(EvaluationError):
        evaluate(pred, table(cars), min_gt_points=5)  # no point counts at all


# ---------------------------------------------------------------------------------------------
# Random scenes against an independent port of OpenPCDet's eval loop


def reference_flags(gt_rows: BoxTable, pred_rows: BoxTable, level: int):
    """clean_data of kitti_object_eval_python for class Car."""
    min_height, max_occ, max_trunc = (40, 25, 25)[level], (0, 1, 2)[level], (0.15, 0.3, 0.5)[level]
    ignored_gt = []
    for k in range(len(gt_rows)):
        name = str(gt_rows["label"][k]).lower()
        valid = 1 if name == "car" else 0 if name == "van" else -1
        height = gt_rows["bbox_bottom"][k] - gt_rows["bbox_top"][k]
        ignore = (
            gt_rows["occluded"][k] > max_occ
            or gt_rows["truncated"][k] > max_trunc
            or height <= min_height
        )
        ignored_gt.append(
            0 if valid == 1 and not ignore else 1 if valid == 0 or (ignore and valid == 1) else -1
        )
    ignored_dt = []
    for k in range(len(pred_rows)):
        height = abs(pred_rows["bbox_bottom"][k] - pred_rows["bbox_top"][k])
        same = str(pred_rows["label"][k]).lower() == "car"
        ignored_dt.append(1 if height < min_height else 0 if same else -1)
    return ignored_gt, ignored_dt


def reference_band_flags(gt_rows: BoxTable, pred_rows: BoxTable, band: tuple):
    """clean_data with a BEV range band in place of the difficulty filters (dali's range protocol):
    Car outside the band is ignored like a too-hard Car, detections outside it like small ones."""
    low, high = band
    ignored_gt = []
    for k in range(len(gt_rows)):
        name = str(gt_rows["label"][k]).lower()
        valid = 1 if name == "car" else 0 if name == "van" else -1
        distance = math.hypot(gt_rows.boxes[k, 0], gt_rows.boxes[k, 1])
        ignore = not low <= distance < high
        ignored_gt.append(
            0 if valid == 1 and not ignore else 1 if valid == 0 or (ignore and valid == 1) else -1
        )
    ignored_dt = []
    for k in range(len(pred_rows)):
        distance = math.hypot(pred_rows.boxes[k, 0], pred_rows.boxes[k, 1])
        same = str(pred_rows["label"][k]).lower() == "car"
        ignored_dt.append(1 if not low <= distance < high else 0 if same else -1)
    return ignored_gt, ignored_dt


def reference_frames(frames, overlap_fn, level, min_overlap, flags=reference_flags):
    """The reference loop's first pass: (per frame (overlaps, scores, ignored_gt, ignored_dt),
    counted ground truths, true-positive scores)."""
    prepared = []
    num_gt = 0
    tp_scores = []
    for gt_rows, pred_rows in frames:
        ignored_gt, ignored_dt = flags(gt_rows, pred_rows, level)
        overlaps = overlap_fn(pred_rows.boxes, gt_rows.boxes)
        scores = [float(s) for s in pred_rows["score"]]
        num_gt += sum(1 for v in ignored_gt if v == 0)
        tp_scores += reference_statistics(
            overlaps, scores, ignored_gt, ignored_dt, min_overlap, 0.0, False
        )[3]
        prepared.append((overlaps, scores, ignored_gt, ignored_dt))
    return prepared, num_gt, tp_scores


def reference_ap(frames, overlap_fn, level, min_overlap, flags=reference_flags):
    """(AP_R40, AP_R11) in percent; `flags(gt_rows, pred_rows, level)` gives the ignore flags."""
    prepared, num_gt, tp_scores = reference_frames(frames, overlap_fn, level, min_overlap, flags)
    thresholds = reference_thresholds(tp_scores, num_gt)
    precision = np.zeros(41)
    for k, thresh in enumerate(thresholds):
        tp = fp = fn = 0
        for overlaps, scores, ignored_gt, ignored_dt in prepared:
            a, b, c, _, _ = reference_statistics(
                overlaps, scores, ignored_gt, ignored_dt, min_overlap, thresh, True
            )
            tp, fp, fn = tp + a, fp + b, fn + c
        precision[k] = tp / (tp + fp)
    precision = np.array([precision[k:].max() for k in range(41)])
    return precision[1:].sum() / 40 * 100, precision[::4].sum() / 11 * 100


def random_scene(
    seed: int, frames: int = 25, crowded: bool = False, max_boxes: int = 8, easy_share: float = 0.0
):
    rng = np.random.default_rng(seed)
    gt_tables, pred_tables = [], []
    for index in range(frames):
        frame = f"{index:04d}"
        count = int(rng.integers(0, max_boxes + 1))
        centre = rng.uniform([2, -20], [60, 20], (count, 2))
        if crowded and count > 1:  # pile objects up so that one detection can hit two labels
            centre[1:] = centre[0] + rng.normal(0, 1.2, (count - 1, 2))
        boxes = np.c_[
            centre,
            rng.uniform(-1.2, -0.6, count),
            rng.normal(CAR, 0.2, (count, 3)),
            rng.uniform(-3.1, 3.1, count),
        ]
        labels = rng.choice(["Car", "Car", "Car", "Car", "Van", "Pedestrian", "DontCare"], count)
        easy = rng.uniform(size=count) < easy_share  # fully visible, 60 px high
        extra = {
            "truncated": np.where(easy, 0.0, rng.uniform(0, 0.6, count)).astype(np.float32),
            "occluded": np.where(easy, 0, rng.integers(0, 4, count)).astype(np.int32),
            "alpha": np.zeros(count),
            "bbox_left": np.zeros(count, np.float32),
            "bbox_top": np.full(count, 100.0, np.float32),
            "bbox_right": np.full(count, 50.0, np.float32),
            "bbox_bottom": (
                100 + np.where(easy, 60.0, rng.choice([20.0, 25.0, 30.0, 40.0, 60.0, 120.0], count))
            ).astype(np.float32),
        }
        gt_tables.append(BoxTable.from_arrays([frame] * count, boxes, label=labels, **extra))
        detected = rng.uniform(size=count) < 0.8
        jitter = np.c_[
            rng.normal(0, 0.25, (count, 3)),
            rng.normal(0, 0.15, (count, 3)),
            rng.normal(0, 0.1, count),
        ]
        found = (boxes + jitter)[detected]
        spurious = int(rng.integers(0, 4))
        fake = np.c_[
            rng.uniform([2, -20], [60, 20], (spurious, 2)),
            np.full(spurious, -0.9),
            np.tile(CAR, (spurious, 1)),
            rng.uniform(-3, 3, spurious),
        ]
        pred = np.r_[found, fake]
        n = len(pred)
        scores = np.round(rng.uniform(0.1, 1.0, n), 2)  # rounded: ties happen
        pred_labels = rng.choice(["Car"] * 9 + ["Pedestrian"], n)
        heights = rng.choice([20.0, 30.0, 45.0, 80.0], n).astype(np.float32)
        pred_extra = {
            "bbox_top": np.full(n, 10.0, np.float32),
            "bbox_bottom": 10 + heights,
        }
        pred_tables.append(
            BoxTable.from_arrays([frame] * n, pred, score=scores, label=pred_labels, **pred_extra)
        )
    return gt_tables, pred_tables


@pytest.mark.parametrize(
    "seed, iou, crowded", [(0, 0.7, False), (1, 0.5, False), (2, 0.3, True), (3, 0.1, True)]
)
def test_matches_reference_loop_on_random_scenes(seed, iou, crowded):
    gt_tables, pred_tables = random_scene(seed, crowded=crowded)
    gt, pred = BoxTable.concat(gt_tables), BoxTable.concat(pred_tables)
    for positions, column in ((40, 0), (11, 1)):
        metrics = evaluate(pred, gt, iou=iou, protocol="kitti", recall_positions=positions)["Car"]
        for metric, overlap_fn in (("bev", geometry.bev_iou), ("3d", geometry.iou_3d)):
            for level, name in enumerate(("easy", "moderate", "hard")):
                expected = reference_ap(
                    list(zip(gt_tables, pred_tables, strict=True)), overlap_fn, level, iou
                )
                assert metrics[metric][name] == pytest.approx(expected[column], abs=1e-9), (
                    metric,
                    name,
                )


def counted_ground_truth(gt_tables, flags, level) -> int:
    return sum(flags(gt, gt.select(np.zeros(len(gt), bool)), level)[0].count(0) for gt in gt_tables)


@pytest.mark.parametrize(
    "seed, frames, iou",
    [(10, 24, 0.7), (11, 28, 0.5), (12, 32, 0.3), (13, 38, 0.7), (14, 44, 0.5), (15, 46, 0.7)],
)
def test_matches_reference_loop_with_42_to_200_counted_ground_truths(seed, frames, iou):
    # above 41 counted ground truths the threshold sampling is easiest to get wrong: scenes
    # across that range, both protocols, every difficulty and band, R40 and R11
    gt_tables, pred_tables = random_scene(
        seed, frames=frames, crowded=seed % 3 == 0, max_boxes=14, easy_share=0.5
    )
    gt, pred = BoxTable.concat(gt_tables), BoxTable.concat(pred_tables)
    scenes = list(zip(gt_tables, pred_tables, strict=True))
    cases = [("kitti", name, reference_flags, level) for level, name in enumerate(DIFFICULTIES)]
    cases += [("range", name, reference_band_flags, band) for name, band in RANGE_BANDS_M.items()]
    counted = {name: counted_ground_truth(gt_tables, flags, key) for _, name, flags, key in cases}
    assert 42 <= min(counted["moderate"], counted["hard"]) <= counted["all"] <= 200, counted
    for positions, column in ((40, 0), (11, 1)):
        results = {
            protocol: evaluate(pred, gt, iou=iou, protocol=protocol, recall_positions=positions)
            for protocol in ("kitti", "range")
        }
        for protocol, name, flags, key in cases:
            metrics = results[protocol]["Car"]
            for metric, overlap_fn in (("bev", geometry.bev_iou), ("3d", geometry.iou_3d)):
                expected = reference_ap(scenes, overlap_fn, key, iou, flags=flags)[column]
                assert metrics[metric][name] == pytest.approx(expected, abs=1e-9), (
                    protocol,
                    name,
                    metric,
                    counted[name],
                )


def test_vectorized_path_handles_a_shared_detection():
    # one wide detection overlapping two labels above IoU 0.3: the greedy label order decides
    gt = np.array([[10.0, 0, 0, 4.0, 2.0, 1.5, 0.0], [10.0, 1.6, 0, 4.0, 2.0, 1.5, 0.0]])
    pred = np.array([[10.0, 0.8, 0, 4.0, 3.0, 1.5, 0.0]])
    assert (geometry.bev_iou(pred, gt) > 0.3).all()
    counts = evaluate(table(pred), table(gt), iou=0.3)["Car"]["counts"]["all"]["bev"]
    assert counts == {"tp": 1, "fp": 0, "fn": 1}


# ---------------------------------------------------------------------------------------------
# label_2 files and the command line


def test_label_files_round_trip_and_evaluate_identically(tmp_path):
    gt_tables, pred_tables = random_scene(5, frames=30)
    gt, pred = BoxTable.concat(gt_tables), BoxTable.concat(pred_tables)
    frames = [f"{k:04d}" for k in range(30)]
    write_label_dir(tmp_path / "gt", gt, frame_ids=frames, with_score=False)
    write_label_dir(tmp_path / "pred", pred, frame_ids=frames)
    assert len(list((tmp_path / "gt").glob("*.txt"))) == 30
    gt_back, pred_back = read_label_dir(tmp_path / "gt"), read_label_dir(tmp_path / "pred")
    assert len(gt_back) == len(gt) and len(pred_back) == len(pred)
    cars = gt["label"] != "DontCare"
    order = np.lexsort((np.arange(len(gt)), gt.frame_id.astype(str)))
    np.testing.assert_allclose(
        gt_back.boxes[cars[order]][:, :6], gt.boxes[order][cars[order]][:, :6], atol=2e-6
    )
    yaw_error = geometry.wrap_angle(gt_back.boxes[:, 6] - gt.boxes[order][:, 6])
    assert np.abs(yaw_error[cars[order]]).max() < 2e-6
    np.testing.assert_array_equal(
        pred_back["score"],
        pred["score"][np.lexsort((np.arange(len(pred)), pred.frame_id.astype(str)))],
    )
    direct = evaluate(pred, gt, protocol="kitti")
    via_files = evaluate(pred_back, gt_back, protocol="kitti", frame_ids=frames)
    for metric in ("bev", "3d"):
        for name in ("easy", "moderate", "hard"):
            assert via_files["Car"][metric][name] == pytest.approx(
                direct["Car"][metric][name], abs=1e-9
            )
    assert via_files["Car"]["counts"] == direct["Car"]["counts"]


def test_label_file_errors_name_the_line(tmp_path):
    path = tmp_path / "000001.txt"
    path.write_text(
        "Car 0 0 0 0 0 50 50 1.5 1.6 3.9 1 1 10 0\nCar 0 0 0 0 0 50 x 1.5 1.6 3.9 1 1 10 0\n"
    )
    with pytest.raises(Exception, match=r"000001.txt:2: field 8"):
        read_label_file(path)
    path.write_text("Car 0 0 0 0 0 50 50 1.5 1.6\n")
    with pytest.raises(Exception, match=r"000001.txt:1: expected 15 or 16 fields"):
        read_label_file(path)


def test_pseudo_lidar_conversion_preserves_iou():
    rng = np.random.default_rng(7)
    a = np.c_[rng.uniform(-10, 10, (200, 3)), rng.uniform(1, 5, (200, 3)), rng.uniform(-3, 3, 200)]
    b = a + np.c_[rng.normal(0, 0.5, (200, 3)), np.zeros((200, 3)), rng.normal(0, 0.2, 200)]
    from dali_cli.importers.kitti_label import camera_to_pseudo_lidar, pseudo_lidar_to_camera

    def converted(boxes):
        # read the LiDAR boxes as if they were camera labels: another rigid frame
        hwl, location, ry = pseudo_lidar_to_camera(boxes)
        return camera_to_pseudo_lidar(hwl, location, ry)

    np.testing.assert_allclose(converted(a)[:, :6], a[:, :6], atol=1e-12)
    swapped = np.c_[a[:, [1, 2, 0]], a[:, 3:6], a[:, 6]]  # permute axes: a different rigid frame
    hwl = swapped[:, [5, 4, 3]]
    camera = camera_to_pseudo_lidar(hwl, swapped[:, :3], swapped[:, 6])
    camera_b = camera_to_pseudo_lidar(b[:, [5, 4, 3]], b[:, [1, 2, 0]], b[:, 6])
    assert np.isfinite(camera).all() and np.isfinite(camera_b).all()
    np.testing.assert_allclose(
        geometry.iou_3d_pairs(converted(a), converted(b)), geometry.iou_3d_pairs(a, b), atol=1e-12
    )


def write_dataset(directory, cars, sensor="kitti"):
    directory.mkdir(parents=True, exist_ok=True)
    frames = [(f"{k:03d}", np.zeros((3, 4), np.float32)) for k in range(len(cars))]
    write_frameset(directory, frames, sensor=sensor)
    write_boxes(
        directory, BoxTable.concat([table(box, frame=f"{k:03d}") for k, box in enumerate(cars)])
    )


def test_cli_tables_labels_and_errors(tmp_path):
    cars = row_of_cars(40)  # 30 of 40 found, precision 1: R40 = 29 / 40 (entry 0 is not used)
    (tmp_path / "gt").mkdir()
    (tmp_path / "pred").mkdir()
    write_boxes(tmp_path / "gt", table(cars))
    write_boxes(tmp_path / "pred", table(cars[:30], score=np.linspace(0.9, 0.2, 30)))
    write_label_dir(tmp_path / "gt_labels", table(cars), with_score=False)
    write_label_dir(tmp_path / "pred_labels", table(cars[:30], score=np.linspace(0.9, 0.2, 30)))
    runner = CliRunner()
    out = tmp_path / "metrics.json"
    result = runner.invoke(
        main,
        ["eval", "--pred", str(tmp_path / "pred"), "--gt", str(tmp_path / "gt"), "--out", str(out)],
    )
    assert result.exit_code == 0, result.output
    assert "AP_BEV" in result.output and "0-30" in result.output
    metrics = json.loads(out.read_text())
    assert metrics["Car"]["iou"] == 0.7 and metrics["Car"]["recall_positions"] == 40
    assert metrics["Car"]["bev"]["all"] == pytest.approx(100 * 29 / 40)
    from_labels = runner.invoke(
        main,
        [
            "eval",
            "--pred",
            str(tmp_path / "pred_labels"),
            "--gt",
            str(tmp_path / "gt_labels"),
            "--protocol",
            "range",
            "--out",
            str(tmp_path / "m2.json"),
        ],
    )
    assert from_labels.exit_code == 0, from_labels.output
    assert json.loads((tmp_path / "m2.json").read_text())["Car"]["bev"] == metrics["Car"]["bev"]
    # bad input: a usage error (2) for a wrong directory, no output file written
    (tmp_path / "empty").mkdir()
    bad = runner.invoke(
        main,
        [
            "eval",
            "--pred",
            str(tmp_path / "empty"),
            "--gt",
            str(tmp_path / "gt"),
            "--out",
            str(tmp_path / "bad.json"),
        ],
    )
    assert bad.exit_code == 2 and "--pred" in bad.output
    assert not (tmp_path / "bad.json").exists()
    assert runner.invoke(main, ["eval", "--gt", str(tmp_path / "gt")]).exit_code == 2
    # kitti protocol on labels without KITTI fields: a clear failure (1)
    no_kitti = runner.invoke(
        main,
        [
            "eval",
            "--pred",
            str(tmp_path / "pred"),
            "--gt",
            str(tmp_path / "gt"),
            "--protocol",
            "kitti",
        ],
    )
    assert no_kitti.exit_code == 1 and "KITTI columns" in no_kitti.output


def keep_runtime(monkeypatch):
    import importlib

    module = importlib.import_module("dali_cli.runtime.machine")
    monkeypatch.setitem(sys.modules, "dali_cli.runtime.machine", module)


def test_cli_model_inference_uses_the_ptsn_scale(tmp_path, monkeypatch):
    cars = [row_of_cars(1) + [0, k, 0, 0, 0, 0, 0] for k in range(45)]
    write_dataset(tmp_path / "data", cars)
    (tmp_path / "ptsn").mkdir()
    (tmp_path / "ptsn" / "scale.json").write_text(json.dumps({"scale": 0.85}))
    seen = {}

    def predict_frameset(model_dir, data_dir, scale=1.0, score_min=0.0, progress=True, **engine):
        seen.update(model=str(model_dir), scale=scale, progress=progress)
        return BoxTable.concat(
            [table(box, frame=f"{k:03d}", score=[0.8]) for k, box in enumerate(cars)]
        )

    fake = types.ModuleType("dali_cli.detector")
    fake.predict_frameset = predict_frameset
    keep_runtime(monkeypatch)  # the machine record of metrics.json stays importable
    monkeypatch.setitem(sys.modules, "dali_cli.detector", fake)
    (tmp_path / "model").mkdir()
    runner = CliRunner()
    args = ["eval", "--model", str(tmp_path / "model"), "--data", str(tmp_path / "data")]
    result = runner.invoke(
        main, [*args, "--scale-from", str(tmp_path / "ptsn"), "--out", str(tmp_path / "m.json")]
    )
    assert result.exit_code == 0, result.output
    assert seen["scale"] == 0.85 and seen["progress"] is True
    quiet = runner.invoke(main, [*args, "--scale", "0.85", "--no-progress"])
    assert quiet.exit_code == 0 and seen["progress"] is False
    metrics = json.loads((tmp_path / "m.json").read_text())["Car"]
    assert metrics["bev"]["all"] == pytest.approx(100.0) and metrics["source"]["scale"] == 0.85
    assert (
        runner.invoke(
            main, [*args, "--scale", "1.1", "--scale-from", str(tmp_path / "ptsn")]
        ).exit_code
        == 2
    )
    (tmp_path / "ptsn" / "scale.json").write_text("{}")
    broken = runner.invoke(main, [*args, "--scale-from", str(tmp_path / "ptsn")])
    assert broken.exit_code == 1 and "scale" in broken.output
    monkeypatch.setitem(sys.modules, "dali_cli.detector", None)  # import fails
    missing = runner.invoke(main, args)
    assert missing.exit_code == 1 and "detector is not available" in missing.output


def test_format_table_lists_every_band():
    cars = row_of_cars(45)
    text = format_table(evaluate(table(cars), table(cars)))
    assert all(band in text for band in ("all", "0-30", "30-50", "50-80"))
    assert math.isclose(float(text.splitlines()[2].split()[1]), 100.0)


def test_empty_inputs():
    cars = row_of_cars(3)
    no_pred = evaluate(BoxTable.empty(), table(cars))["Car"]
    assert no_pred["bev"]["all"] == 0.0 and no_pred["counts"]["all"]["bev"] == {
        "tp": 0,
        "fp": 0,
        "fn": 3,
    }
    no_gt = evaluate(table(cars), BoxTable.empty())["Car"]
    assert no_gt["bev"]["all"] is None and no_gt["counts"]["all"]["bev"] == {
        "tp": 0,
        "fp": 3,
        "fn": 0,
    }
    nothing = evaluate(BoxTable.empty(), BoxTable.empty(), frame_ids=["a", "b"])["Car"]
    assert nothing["frames"] == 2 and nothing["3d"]["all"] is None
    with pytest.raises(EvaluationError, match="outside the evaluated frames"):
        evaluate(table(cars, frame="c"), BoxTable.empty(), frame_ids=["a", "b"])


def test_float32_label_fields_compare_like_the_decimal_text():
    # truncation 0.15 and a 2D box 174.34..214.34 (40 px) stored as float32, as label files give
    cars = row_of_cars(3)
    extra = kitti_columns(3)
    extra["truncated"] = np.array([0.15, 0.16, 0.0], np.float32)
    extra["bbox_top"] = np.array([0.0, 0.0, 174.34], np.float32)
    extra["bbox_bottom"] = np.array([100.0, 100.0, 214.34], np.float32)
    counts = evaluate(table(cars), table(cars, **extra), protocol="kitti")["Car"]["counts"]
    assert counts["easy"]["gt"] == 1  # 0.16 is too truncated, 40.0 px is not > 40
    assert counts["moderate"]["gt"] == 3


KITTI_FIXTURE = Path(__file__).resolve().parent / "fixtures" / "real" / "kitti" / "training"


@pytest.mark.skipif(
    not KITTI_FIXTURE.is_dir(), reason="KITTI fixture (tests/fixtures/real) not found"
)
def test_real_kitti_label_file_difficulties():
    # frame 000008: 6 cars, 4 DontCare. By hand from the label fields (trunc, occ, 2D height):
    # car 1 trunc .88 and car 3 occ 3 are ignored at every level; car 2 (occ 1, 193 px) and
    # car 4 (occ 1, 85 px) are moderate; car 5 (39.6 px) is moderate; car 6 (62 px) is easy.
    labels = read_label_file(KITTI_FIXTURE / "label_2" / "000008.txt")
    assert len(labels) == 10 and (labels["label"] == "DontCare").sum() == 4
    assert labels.frame_id[0] == "000008"
    metrics = evaluate(labels, labels, protocol="kitti")["Car"]
    assert [metrics["counts"][name]["gt"] for name in ("easy", "moderate", "hard")] == [1, 4, 4]
    assert [metrics["counts"][name]["gt_ignored"] for name in ("easy", "moderate", "hard")] == [
        5,
        2,
        2,
    ]
    for name, valid in (("easy", 1), ("moderate", 4), ("hard", 4)):
        assert metrics["counts"][name]["bev"] == {"tp": valid, "fp": 0, "fn": 0}
        assert metrics["bev"][name] == pytest.approx(100 * (valid - 1) / 40)  # R40 with < 41 cars


def test_cli_several_ious_sizes_and_saved_predictions(tmp_path, monkeypatch):
    cars = [row_of_cars(1) + [0, k, 0, 0, 0, 0, 0] for k in range(45)]
    write_dataset(tmp_path / "data", cars)
    # predictions 10 % too long: a true positive at IoU 0.5 (BEV IoU 1/1.1), at 0.7 too
    grown = [np.asarray(box, float) * [1, 1, 1, 1.1, 1, 1, 1] for box in cars]
    scores = np.r_[np.full(40, 0.8), np.full(5, 0.1)]

    def predict_frameset(model_dir, data_dir, scale=1.0, score_min=0.0, progress=True, **engine):
        return BoxTable.concat(
            [table(box, frame=f"{k:03d}", score=[scores[k]]) for k, box in enumerate(grown)]
        )

    fake = types.ModuleType("dali_cli.detector")
    fake.predict_frameset = predict_frameset
    keep_runtime(monkeypatch)  # the machine record of metrics.json stays importable
    monkeypatch.setitem(sys.modules, "dali_cli.detector", fake)
    (tmp_path / "model").mkdir()
    out = tmp_path / "eval" / "metrics.json"
    args = ["eval", "--model", str(tmp_path / "model"), "--data", str(tmp_path / "data")]
    result = CliRunner().invoke(
        main, [*args, "--iou", "0.7", "--iou", "0.95", "--scale", "1.2", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    metrics = json.loads(out.read_text())
    assert metrics["Car"]["iou"] == 0.7 and metrics["Car"]["bev"]["all"] == pytest.approx(100.0)
    assert metrics["Car@0.95"]["iou"] == 0.95 and metrics["Car@0.95"]["bev"]["all"] == 0.0
    truth = np.asarray(cars, float).reshape(-1, 7)
    assert metrics["sizes"]["gt"] == pytest.approx(truth[:, 3:6].mean(axis=0), abs=1e-4)
    # only the 40 predictions with score >= 0.3 enter the mean predicted size
    expected = (truth[:40, 3:6] * [1.1, 1, 1]).mean(axis=0)
    assert metrics["sizes"]["pred"] == pytest.approx(expected, abs=1e-4)
    assert metrics["scale"] == 1.2
    saved = read_boxes(out.parent / "predictions.parquet")
    assert len(saved) == 45 and np.allclose(saved.boxes, np.asarray(grown).reshape(-1, 7))
    # a repeated threshold is a usage error and writes nothing
    again = CliRunner().invoke(
        main, [*args, "--iou", "0.7", "--iou", "0.7", "--out", str(tmp_path / "x" / "m.json")]
    )
    assert again.exit_code == 2 and not (tmp_path / "x").exists()


def test_eval_directory_is_a_manifest_tracked_artifact(tmp_path):
    """`dali eval --out DIR`: metrics.json + manifest.json under the stage contract; a rerun with
    the same inputs is skipped, a KITTI metrics file added later does not make it stale, changed
    inputs or parameters rerun it, and an older run's plain eval directory may be replaced."""
    from dali_cli.store.manifest import read_manifest

    cars = row_of_cars(20)
    for name, rows, score in (("gt", cars, None), ("pred", cars[:15], np.linspace(0.9, 0.3, 15))):
        (tmp_path / name).mkdir()
        write_boxes(tmp_path / name, table(rows, score=score))
    runner = CliRunner()
    out = tmp_path / "run" / "eval"
    args = [
        "eval",
        "--pred",
        str(tmp_path / "pred"),
        "--gt",
        str(tmp_path / "gt"),
        "--out",
        str(out),
    ]
    first = runner.invoke(main, args)
    assert first.exit_code == 0, first.output
    manifest = read_manifest(out)
    assert manifest["stage"] == "eval" and set(manifest["inputs"]) == {"pred", "gt"}
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["Car"]["bev"]["all"] == pytest.approx(100 * 14 / 40)
    assert "AP_BEV" in first.output
    (out / "metrics_kitti.json").write_text("{}")  # what `make kitti-protocol` adds beside it
    again = runner.invoke(main, args)
    assert again.exit_code == 0 and "up to date" in again.output and "AP_BEV" in again.output
    changed = runner.invoke(main, [*args, "--iou", "0.5"])
    assert changed.exit_code == 0 and "up to date" not in changed.output
    assert json.loads((out / "metrics.json").read_text())["Car"]["iou"] == 0.5
    assert not (out / "metrics_kitti.json").exists()  # rebuilt as a whole
    write_boxes(tmp_path / "pred", table(cars[:10], score=np.linspace(0.9, 0.3, 10)))
    rerun = runner.invoke(main, [*args, "--iou", "0.5"])
    assert rerun.exit_code == 0 and "up to date" not in rerun.output
    assert (
        json.loads((out / "metrics.json").read_text())["Car"]["counts"] != metrics["Car"]["counts"]
    )
    # an evaluation directory of an older run (no manifest) is replaced; a user's is refused
    legacy = tmp_path / "old" / "eval"
    legacy.mkdir(parents=True)
    (legacy / "metrics.json").write_text(json.dumps({"Car": {"bev": {}}, "sizes": {}}))
    replaced = runner.invoke(main, [*args[:-1], str(legacy)])
    assert replaced.exit_code == 0, replaced.output
    assert read_manifest(legacy)["stage"] == "eval"
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    refused = runner.invoke(main, [*args[:-1], str(mine)])
    assert refused.exit_code == 1 and (mine / "notes.txt").read_text() == "keep me"


# ---------------------------------------------------------------------------------------------
# R400: the precision at the recall values k / 400, thresholded at every true-positive score


def reference_ap_by_recall(frames, overlap_fn, level, min_overlap, positions=400):
    """AP over the recall values k / positions with the reference loop's counts at every distinct
    true-positive score (the largest precision at any threshold whose recall reaches k / N)."""
    prepared, num_gt, tp_scores = reference_frames(frames, overlap_fn, level, min_overlap)
    points = []  # (recall, precision) at each threshold
    for thresh in sorted(set(tp_scores), reverse=True):
        tp = fp = 0
        for overlaps, scores, ignored_gt, ignored_dt in prepared:
            a, b, _, _, _ = reference_statistics(
                overlaps, scores, ignored_gt, ignored_dt, min_overlap, thresh, True
            )
            tp, fp = tp + a, fp + b
        points.append((tp / num_gt, tp / (tp + fp)))
    total = 0.0
    for k in range(1, positions + 1):
        reaching = [p for r, p in points if r >= k / positions - 1e-12]
        total += max(reaching, default=0.0)
    return total / positions * 100


def test_fine_recall_grid_tracks_the_maximum_recall_where_r40_steps():
    """100 cars, no false box: R400 is the recall found (in steps of 1/400); R40 jumps to the next
    k/40 as soon as the recall passes one (the reference's sampling takes the last true positive
    as the threshold of the position above), so 86 and 88 cars found score alike."""
    cars = row_of_cars(100, spacing=6.0)
    for found, r40, r400 in ((85, 85.0, 85.0), (86, 87.5, 86.0), (88, 87.5, 88.0)):
        pred = table(cars[:found], score=np.linspace(0.95, 0.3, found))
        truth = table(cars)
        assert evaluate(pred, truth)["Car"]["3d"]["all"] == pytest.approx(r40)
        fine = evaluate(pred, truth, recall_positions=400)["Car"]
        assert fine["3d"]["all"] == pytest.approx(r400) and fine["recall_positions"] == 400
    few = row_of_cars(20)  # R40: 100 x 19 / 40 for a perfect detector of 20 cars
    assert evaluate(table(few, score=np.linspace(0.9, 0.5, 20)), table(few),
                    recall_positions=400)["Car"]["bev"]["all"] == pytest.approx(100.0)  # fmt: skip
    pred, scores, truth = known_curve_scene()  # precision 1 to recall 0.5, then at best 0.8
    fine = evaluate(table(pred, score=scores), table(truth), recall_positions=400)["Car"]
    assert fine["bev"]["all"] == pytest.approx((200 * 1.0 + 200 * 0.8) / 400 * 100)
    assert len(fine["curves"]["bev"]["all"]["precision"]) == 401


@pytest.mark.parametrize("seed, iou, crowded", [(0, 0.7, False), (2, 0.3, True), (4, 0.5, False)])
def test_fine_recall_grid_matches_the_reference_loop(seed, iou, crowded):
    gt_tables, pred_tables = random_scene(seed, crowded=crowded)
    gt, pred = BoxTable.concat(gt_tables), BoxTable.concat(pred_tables)
    metrics = evaluate(pred, gt, iou=iou, protocol="kitti", recall_positions=400)["Car"]
    frames = list(zip(gt_tables, pred_tables, strict=True))
    for metric, overlap_fn in (("bev", geometry.bev_iou), ("3d", geometry.iou_3d)):
        for level, name in enumerate(("easy", "moderate", "hard")):
            expected = reference_ap_by_recall(frames, overlap_fn, level, iou)
            assert metrics[metric][name] == pytest.approx(expected, abs=1e-9), (metric, name)


def dense_counts_at_levels(
    pairs, scores, ignored_gt, ignored_pred, levels, in_loop_gt, in_loop_pred
):
    """The matching pass written level by level (the former (L, E) implementation): at each level
    every ground truth takes its first candidate, by the same preference, with score >= level."""
    pred_index, gt_index, overlap = pairs
    pred_ignored = ignored_pred[pred_index]
    order = np.lexsort(
        (pred_index, np.where(pred_ignored == 0, -overlap, 0.0), pred_ignored, gt_index)
    )
    tp, fp, fn = [], [], []
    eligible = scores[(ignored_pred == 0) & ~in_loop_pred]
    for level in levels:
        taken = {}
        for e in order:
            if scores[pred_index[e]] >= level and gt_index[e] not in taken:
                taken[gt_index[e]] = pred_index[e]
        counted = [g for g in range(len(ignored_gt)) if ignored_gt[g] == 0 and not in_loop_gt[g]]
        tp.append(sum(1 for g in counted if g in taken and ignored_pred[taken[g]] == 0))
        fn.append(sum(1 for g in counted if g not in taken))
        fp.append(
            int(np.sum(eligible >= level)) - sum(ignored_pred[p] == 0 for p in taken.values())
        )
    return np.array(tp), np.array(fp), np.array(fn)


@pytest.mark.parametrize("seed", range(6))
def test_matching_pass_by_intervals_equals_the_level_by_level_pass(seed):
    """_counts_at_levels counts each candidate over the score interval in which it is taken;
    it must give the level-by-level counts, with tied scores and overlaps, ignored predictions
    and ground truths, and levels between and at the scores."""
    from dali_cli.evaluation.evaluate import _counts_at_levels

    rng = np.random.default_rng(seed)
    for trial in range(60):
        num_pred, num_gt = int(rng.integers(1, 25)), int(rng.integers(1, 25))
        pairs = np.unique(
            rng.integers(0, [num_pred, num_gt], (int(rng.integers(0, 50)), 2)), axis=0
        )
        pred_index, gt_index = pairs[:, 0], pairs[:, 1]
        tied = trial % 2 == 0
        overlap = rng.choice([0.6, 0.8], len(pairs)) if tied else rng.uniform(0.5, 1, len(pairs))
        scores = rng.choice([0.2, 0.5, 0.9], num_pred) if tied else rng.uniform(0, 1, num_pred)
        ignored_gt = rng.choice([0, 1], num_gt, p=[0.8, 0.2])
        ignored_pred = rng.choice([0, 1], num_pred, p=[0.8, 0.2])
        in_loop_gt = np.zeros(num_gt, bool)
        in_loop_pred = np.zeros(num_pred, bool)
        levels = np.r_[np.unique(np.r_[scores, rng.uniform(0, 1, 4)])[::-1], -np.inf]
        args = ((pred_index, gt_index, overlap), scores, ignored_gt, ignored_pred, levels)
        fast = _counts_at_levels(*args, in_loop_gt, in_loop_pred)
        dense = dense_counts_at_levels(*args, in_loop_gt, in_loop_pred)
        for got, expected, name in zip(fast[:3], dense, ("tp", "fp", "fn"), strict=True):
            np.testing.assert_array_equal(got, expected, err_msg=f"{name}, trial {trial}")
        # weighted by 1 per pair, the heading metrics' true positives are the true positives
        ones = _counts_at_levels(*args, in_loop_gt, in_loop_pred, np.ones(len(pairs)))
        np.testing.assert_allclose(ones[3], dense[0], err_msg=f"weighted tp, trial {trial}")
