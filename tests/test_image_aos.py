"""KITTI's image side of `dali eval` (dali_cli/evaluation/image.py): predictions' 2D boxes and
alpha from the calibration, AP_2D and AOS on the image matches (perfect, turned by pi, off in
depth, alpha rather than yaw, DontCare regions), an independent port of the reference loop's AOS,
and `dali eval --calib`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from kitti_reference import reference_statistics, reference_thresholds

from dali_cli.cli import main
from dali_cli.evaluation.evaluate import evaluate, format_table
from dali_cli.evaluation.image import image_overlap, with_image_boxes
from dali_cli.geometry import wrap_angle
from dali_cli.importers.kitti import read_calib
from dali_cli.store.artifacts import BoxTable, write_boxes

CALIB_FILE = (
    Path(__file__).parent / "fixtures" / "real" / "kitti" / "training" / "calib" / "000008.txt"
)
CALIB = read_calib(CALIB_FILE)
CAR = (3.9, 1.6, 1.5)


def cars_ahead(count: int, seed: int = 0) -> np.ndarray:
    """`count` LiDAR-frame cars `(count, 7)` 8-25 m ahead in the camera's view, any heading."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(8.0, 25.0, count)
    return np.c_[
        x, rng.uniform(-0.2, 0.2, count) * x, np.full(count, -0.9), np.tile(CAR, (count, 1)),
        rng.uniform(-np.pi, np.pi, count),
    ]  # fmt: skip


def frames_of(boxes: np.ndarray, score=None, ids=None, **extra) -> BoxTable:
    """One box a frame (frames 000000, 000001, ... unless `ids` says), through the
    calibration's camera."""
    ids = [f"{k:06d}" for k in range(len(boxes))] if ids is None else ids
    score = np.full(len(boxes), -1.0) if score is None else score
    table = BoxTable.from_arrays(ids, boxes, score=score, label="Car", **extra)
    return with_image_boxes(table, lambda frame_id: CALIB)


def ground_truth(boxes: np.ndarray, ids=None) -> BoxTable:
    count = len(boxes)
    return frames_of(boxes, ids=ids, truncated=np.zeros(count, np.float32),
                     occluded=np.zeros(count, np.int32))  # fmt: skip


def scored(pred_boxes: np.ndarray, truth: np.ndarray, **pred_columns) -> dict:
    score = np.linspace(0.9, 0.5, len(pred_boxes))
    pred = frames_of(pred_boxes, score)
    if pred_columns:
        pred = pred.with_columns(**pred_columns)
    return evaluate(pred, ground_truth(truth), protocol="kitti")["Car"]


def test_a_perfect_detector_scores_full_marks_on_the_image_side():
    truth = cars_ahead(40)
    result = scored(truth, truth)
    assert result["aos_matching"] == "image" and result["bbox_iou"] == 0.7
    for name in ("easy", "moderate", "hard"):
        assert result["bbox"][name] == pytest.approx(result["bev"][name])
        assert result["aos"][name] == pytest.approx(result["bbox"][name])
    assert result["bbox"]["moderate"] == pytest.approx(result["counts"]["moderate"]["ap_ceiling"])


def test_every_box_turned_around_keeps_its_image_ap_and_scores_zero_aos():
    truth = cars_ahead(40)
    turned = truth.copy()
    turned[:, 6] = wrap_angle(turned[:, 6] + np.pi)
    result, perfect = scored(turned, truth), scored(truth, truth)
    assert result["bbox"]["moderate"] == pytest.approx(perfect["bbox"]["moderate"])
    assert result["aos"]["moderate"] == pytest.approx(0.0, abs=1e-9)


def test_aos_follows_the_image_matches_not_the_bev_ones():
    """A box 1.2 m too far along the viewing ray misses its car in BEV at IoU 0.7 but covers it
    in the image: KITTI's AOS counts it."""
    truth = cars_ahead(40)
    truth[:, 6] = 0.0  # along the ray: the depth error is all along the car's length
    far = truth.copy()
    far[:, :2] *= (1 + 1.2 / np.hypot(truth[:, 0], truth[:, 1]))[:, None]
    result = scored(far, truth)
    assert result["bev"]["moderate"] == 0.0
    assert result["bbox"]["moderate"] > 80.0
    assert result["aos"]["moderate"] == pytest.approx(result["bbox"]["moderate"], rel=1e-3)
    bev_only = evaluate(
        BoxTable.from_arrays(
            [f"{k:06d}" for k in range(len(far))], far, score=np.linspace(0.9, 0.5, len(far)),
            label="Car",
        ),
        ground_truth(truth), protocol="kitti",
    )["Car"]  # fmt: skip
    assert bev_only["aos_matching"] == "bev" and bev_only["aos"]["moderate"] == 0.0
    assert "bbox" not in bev_only


def test_aos_weighs_the_observation_angle_not_the_yaw():
    truth = cars_ahead(40)
    perfect = scored(truth, truth)
    truth_alpha = ground_truth(truth)["alpha"]
    result = scored(truth, truth, alpha=wrap_angle(truth_alpha + np.pi / 3).astype(np.float32))
    assert result["bbox"]["moderate"] == pytest.approx(perfect["bbox"]["moderate"])
    assert result["aos"]["moderate"] == pytest.approx(0.75 * perfect["bbox"]["moderate"], rel=1e-5)
    assert result["aph"]["moderate"] == pytest.approx(perfect["aph"]["moderate"])


def test_a_false_box_in_a_dont_care_region_costs_the_image_ap_nothing():
    truth = cars_ahead(20)
    gt = ground_truth(truth)
    stray = np.array([[15.0, -1.0, -0.9, *CAR, 0.0]])  # a box of frame 000000, no car there
    region = with_image_boxes(
        BoxTable.from_arrays(["000000"], stray, score=np.array([-1.0]), label="Car"),
        lambda frame_id: CALIB,
    )
    left, top, right, bottom = (
        float(region[k][0]) for k in ("bbox_left", "bbox_top", "bbox_right", "bbox_bottom")
    )
    dont_care = BoxTable.from_arrays(
        ["000000"], np.zeros((1, 7)), score=np.array([-1.0]), label="DontCare",
        truncated=np.array([-1.0], np.float32), occluded=np.array([-1], np.int32),
    ).with_columns(
        bbox_left=np.array([left - 5], np.float32), bbox_top=np.array([top - 5], np.float32),
        bbox_right=np.array([right + 5], np.float32),
        bbox_bottom=np.array([bottom + 5], np.float32), alpha=np.array([-10.0], np.float32),
    )  # fmt: skip
    boxes = np.r_[stray, truth]
    pred = frames_of(truth, np.linspace(0.9, 0.5, len(truth)))
    pred = BoxTable.concat([
        with_image_boxes(BoxTable.from_arrays(["000000"], stray, score=np.array([0.95]),
                                              label="Car"), lambda frame_id: CALIB),
        pred,
    ])  # fmt: skip
    with_region = evaluate(pred, BoxTable.concat([gt, dont_care]), protocol="kitti")["Car"]
    without = evaluate(pred, gt, protocol="kitti")["Car"]
    assert len(boxes) == len(pred)
    ceiling = with_region["counts"]["moderate"]["ap_ceiling"]
    assert without["bbox"]["moderate"] < ceiling - 1  # the stray box is a false positive ...
    assert with_region["bbox"]["moderate"] == pytest.approx(ceiling)  # ... but not in DontCare
    assert with_region["bev"]["moderate"] == pytest.approx(without["bev"]["moderate"])


def test_image_overlap_at_hand_computed_boxes():
    a = np.array([[0.0, 0.0, 10.0, 10.0], [0.0, 0.0, 10.0, 10.0], [0.0, 0.0, 10.0, 10.0]])
    b = np.array([[5.0, 0.0, 15.0, 10.0], [20.0, 0.0, 30.0, 10.0], [0.0, 0.0, 20.0, 20.0]])
    np.testing.assert_allclose(image_overlap(a, b), [50 / 150, 0.0, 100 / 400])
    np.testing.assert_allclose(image_overlap(a, b, "first"), [0.5, 0.0, 1.0])


# --- an independent port of OpenPCDet's kitti_object_eval_python AOS (eval_class, metric 0) ---


def reference_aos(frames, min_overlap=0.7, min_height=25):
    """(AP_2D, AOS) R40 in percent of [(gt_boxes2d, gt_alpha, pred_boxes2d, pred_alpha,
    scores)] per frame, every object a Car that is not occluded or truncated (moderate)."""

    def prepare(gt2d, gt_alpha, dt2d, dt_alpha, scores):
        """A frame's reference_statistics inputs but the threshold: computed once."""
        ignored_gt = [0 if b[3] - b[1] > min_height else 1 for b in gt2d]
        ignored_dt = [1 if abs(b[3] - b[1]) < min_height else 0 for b in dt2d]
        pairs = image_overlap(np.repeat(dt2d, len(gt2d), axis=0), np.tile(gt2d, (len(dt2d), 1)))
        similarity = (1 + np.cos(np.subtract.outer(dt_alpha, gt_alpha))) / 2  # [j, i]
        overlaps = pairs.reshape(len(dt2d), len(gt2d))
        return overlaps, list(scores), ignored_gt, ignored_dt, similarity

    prepared = [prepare(*frame) for frame in frames]
    num_gt = sum(int(np.sum(f[0][:, 3] - f[0][:, 1] > min_height)) for f in frames)
    tp_scores = [
        score
        for overlaps, scores, ignored_gt, ignored_dt, similarity in prepared
        for score in reference_statistics(
            overlaps, scores, ignored_gt, ignored_dt, min_overlap, 0.0, False, similarity
        )[3]
    ]
    chosen = reference_thresholds(tp_scores, num_gt)
    precision, aos = np.zeros(41), np.zeros(41)
    for k, thresh in enumerate(chosen):
        tp = fp = 0
        similar = 0.0
        for overlaps, scores, ignored_gt, ignored_dt, similarity in prepared:
            a, b, _, _, s = reference_statistics(
                overlaps, scores, ignored_gt, ignored_dt, min_overlap, thresh, True, similarity
            )
            tp, fp, similar = tp + a, fp + b, similar + s
        precision[k], aos[k] = tp / (tp + fp), similar / (tp + fp)
    precision = np.array([precision[k:].max() for k in range(41)])
    aos = np.array([aos[k:].max() for k in range(41)])
    return precision[1:].sum() / 40 * 100, aos[1:].sum() / 40 * 100


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_image_side_matches_the_reference_loop_on_random_scenes(seed):
    rng = np.random.default_rng(seed)
    gt_tables, pred_tables, frames = [], [], []
    for frame in range(12):
        truth = cars_ahead(int(rng.integers(1, 5)), seed=seed * 100 + frame)
        pred = truth[rng.random(len(truth)) < 0.8].copy()
        pred[:, :2] += rng.normal(0, 0.3, (len(pred), 2))
        pred[:, 6] += rng.normal(0, 0.4, len(pred)) + np.pi * (rng.random(len(pred)) < 0.3)
        pred = np.r_[pred, cars_ahead(int(rng.integers(0, 3)), seed=seed * 100 + frame + 50)]
        ids = [f"{frame:06d}"]
        gt = ground_truth(truth, ids=ids * len(truth))
        scores = rng.uniform(0.1, 1.0, len(pred))
        detections = frames_of(pred, scores, ids=ids * len(pred))
        gt_tables.append(gt)
        pred_tables.append(detections)

        def image(table):
            return np.stack([np.asarray(table[k], np.float64) for k in
                             ("bbox_left", "bbox_top", "bbox_right", "bbox_bottom")], axis=1)  # fmt: skip

        frames.append((image(gt), np.asarray(gt["alpha"], np.float64), image(detections),
                       np.asarray(detections["alpha"], np.float64), list(scores)))  # fmt: skip
    result = evaluate(BoxTable.concat(pred_tables), BoxTable.concat(gt_tables), protocol="kitti")
    ap_2d, aos = reference_aos(frames)
    assert result["Car"]["bbox"]["moderate"] == pytest.approx(ap_2d, abs=1e-6)
    assert result["Car"]["aos"]["moderate"] == pytest.approx(aos, abs=1e-6)


def test_dali_eval_with_calib_scores_the_image_side(tmp_path):
    truth = cars_ahead(30)
    (tmp_path / "gt").mkdir()
    (tmp_path / "pred").mkdir()
    write_boxes(tmp_path / "gt", ground_truth(truth))
    pred = BoxTable.from_arrays([f"{k:06d}" for k in range(len(truth))], truth,
                                score=np.linspace(0.9, 0.5, len(truth)), label="Car")  # fmt: skip
    write_boxes(tmp_path / "pred", pred)
    runner = CliRunner()
    args = ["eval", "--pred", str(tmp_path / "pred"), "--gt", str(tmp_path / "gt"),
            "--protocol", "kitti"]  # fmt: skip
    with_calib = runner.invoke(main, [*args, "--calib", str(CALIB_FILE), "--out",
                                      str(tmp_path / "m.json")])  # fmt: skip
    assert with_calib.exit_code == 0, with_calib.output
    assert "AP_2D" in with_calib.output and "on the image matches" in with_calib.output
    metrics = json.loads((tmp_path / "m.json").read_text())["Car"]
    assert metrics["aos_matching"] == "image"
    assert metrics["aos"]["moderate"] == pytest.approx(metrics["bbox"]["moderate"])
    without = runner.invoke(main, args)
    assert without.exit_code == 0 and "AP_2D" not in without.output
    missing = runner.invoke(main, [*args, "--calib", str(tmp_path)])  # no <frame>.txt there
    assert missing.exit_code != 0 and "000000.txt" in missing.output
    assert "calib file missing for frame '000000'" in missing.output


def test_format_table_names_where_aos_was_matched():
    truth = cars_ahead(10)
    text = format_table({"Car": scored(truth, truth)})
    assert "AP_2D" in text and "on the image matches at 2D IoU > 0.7" in text
