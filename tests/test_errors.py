"""The error breakdown: box errors known by construction, the false-positive kinds, the AP each
fix gains, its agreement with the evaluator's counts, and `dali eval` / `dali report` with it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from test_evaluate import kitti_columns, random_scene

from dali_cli.cli import main
from dali_cli.evaluation.errors import (
    ERROR_BANDS_M,
    FIXES,
    KINDS,
    QUANTITIES,
    box_errors,
    breakdown,
    format_breakdown,
    size_spread,
    summarize,
    turned_around,
)
from dali_cli.evaluation.evaluate import evaluate
from dali_cli.store.artifacts import BoxTable, write_boxes
from dali_cli.store.manifest import MANIFEST_NAME, hash_tree
from stages.eval import KITTI_METRICS_NAME

CAR = (3.9, 1.6, 1.5)


def cars_around(count: int, seed: int = 0, heading_out: bool = False) -> np.ndarray:
    """`count` cars `(count, 7)` at 5-60 m in every direction, random yaw (or, `heading_out`,
    along the range direction, so that a move along it slides a car along its length)."""
    rng = np.random.default_rng(seed)
    distance = rng.uniform(5, 60, count)
    azimuth = rng.uniform(-np.pi, np.pi, count)
    return np.c_[
        distance * np.cos(azimuth),
        distance * np.sin(azimuth),
        np.full(count, -0.9),
        np.tile(CAR, (count, 1)),
        azimuth if heading_out else rng.uniform(-np.pi, np.pi, count),
    ]


def one_per_frame(boxes, score=None, first: int = 0) -> BoxTable:
    frames = [f"{first + k:04d}" for k in range(len(boxes))]
    return BoxTable.from_arrays(frames, np.asarray(boxes, float).reshape(-1, 7), score=score)


def moved_along_range(boxes: np.ndarray, metres: float) -> np.ndarray:
    moved = boxes.copy()
    moved[:, :2] *= (1 + metres / np.hypot(boxes[:, 0], boxes[:, 1]))[:, None]
    return moved


# ---------------------------------------------------------------------------------------------
# Box errors


def test_a_box_moved_along_its_range_has_a_radial_error_only():
    truth = cars_around(200)
    errors = box_errors(moved_along_range(truth, 0.3), truth)
    assert errors.shape == (200, len(QUANTITIES))
    assert np.allclose(errors[:, 0], 0.3) and np.allclose(errors[:, 1:], 0, atol=1e-12)
    # towards the sensor: negative
    assert np.allclose(box_errors(moved_along_range(truth, -0.5), truth)[:, 0], -0.5)


def test_a_box_moved_across_its_range_has_a_tangential_error_only():
    truth = cars_around(200, seed=1)
    distance = np.hypot(truth[:, 0], truth[:, 1])
    left = np.c_[-truth[:, 1], truth[:, 0]] / distance[:, None]  # counter-clockwise unit vector
    moved = truth.copy()
    moved[:, :2] += 0.2 * left
    errors = box_errors(moved, truth)
    assert np.allclose(errors[:, 1], 0.2) and np.allclose(errors[:, 0], 0, atol=1e-12)


def test_sizes_height_and_yaw_errors():
    truth = cars_around(50, seed=2)
    changed = truth + [0, 0, 0.1, -0.2, 0.05, 0.15, np.radians(3)]
    errors = box_errors(changed, truth)
    assert np.allclose(errors[:, 2:6], [0.1, -0.2, 0.05, 0.15])
    assert np.allclose(errors[:, 6], 3.0)
    # a box turned around has the right axis (what the overlap sees) but faces backwards
    flipped = truth.copy()
    flipped[:, 6] += np.pi + np.radians(2)
    assert np.allclose(box_errors(flipped, truth)[:, 6], 2.0)
    assert turned_around(flipped, truth).all() and not turned_around(changed, truth).any()
    # the wrap: 359 deg apart is 1 deg apart; 91 deg apart is an axis 89 deg off the other way
    across = truth.copy()
    across[:, 6] = truth[:, 6] + np.radians(359)
    assert np.allclose(box_errors(across, truth)[:, 6], -1.0)
    across[:, 6] = truth[:, 6] + np.radians(91)
    assert np.allclose(box_errors(across, truth)[:, 6], -89.0)
    assert turned_around(across, truth).all()


def test_a_box_at_the_sensor_takes_the_x_axis_as_its_ray():
    truth = np.array([[0.0, 0, 0, *CAR, 0]])
    assert np.allclose(box_errors(truth + [0.4, 0.1, 0, 0, 0, 0, 0], truth)[0, :2], [0.4, 0.1])


def test_summary_of_a_symmetric_and_a_shifted_sample():
    values = np.linspace(-1, 1, 101)
    stats = summarize(values + 0.25)
    assert stats["median"] == pytest.approx(0.25) and stats["mean"] == pytest.approx(0.25)
    assert stats["p16"] == pytest.approx(0.25 - 0.68) and stats["p84"] == pytest.approx(0.25 + 0.68)
    assert stats["median_abs"] == pytest.approx(0.5, abs=0.02)
    assert set(summarize(np.zeros(0)).values()) == {None}


def test_size_spread_tells_one_size_for_every_car_from_sizes_that_follow_the_cars():
    rng = np.random.default_rng(0)
    truth = np.zeros((200, 7))
    truth[:, 3] = rng.uniform(3.2, 5.0, 200)  # lengths as varied as KITTI's cars
    truth[:, 4] = rng.uniform(1.5, 1.9, 200)
    same = truth.copy()
    same[:, 3], same[:, 4] = 3.9, 1.6  # every car the same box
    follows = truth.copy()
    follows[:, 3] += rng.normal(0, 0.05, 200)
    one_size, per_car = size_spread(same, truth), size_spread(follows, truth)
    assert one_size["l_m"]["spread_ratio"] == pytest.approx(0.0, abs=1e-9)
    assert per_car["l_m"]["spread_ratio"] == pytest.approx(1.0, abs=0.1)
    assert per_car["l_m"]["labels"]["p5"] == pytest.approx(np.percentile(truth[:, 3], 5), abs=1e-4)
    assert per_car["w_m"]["spread_ratio"] == pytest.approx(1.0)  # widths kept exactly
    assert size_spread(truth[:1], truth[:1])["l_m"]["spread_ratio"] is None
    _, gt, pred = scene()
    assert "l spread: predicted" in format_breakdown(breakdown(pred, gt))


# ---------------------------------------------------------------------------------------------
# The breakdown of a scene built with known errors


def scene():
    """60 cars one per frame; 45 found 0.3 m too far, one found 1.7 m off (mislocalized),
    14 missed; a duplicate of a found car and a box where no car is (background)."""
    truth = cars_around(60, seed=3, heading_out=True)  # 0.3 m along a car: IoU 3.6 / 4.2
    found = moved_along_range(truth[:45], 0.3)
    off = truth[45].copy()
    off[:2] += 1.7 * truth[45, :2] / np.hypot(*truth[45, :2])
    duplicate = moved_along_range(found[:1], 0.1)[0]  # a second, worse box on a found car
    nowhere = truth[1].copy()
    nowhere[:2] *= -1  # the car mirrored through the sensor: overlaps nothing in its frame
    pred = BoxTable.concat(
        [
            one_per_frame(found, score=np.linspace(0.95, 0.5, 45)),
            one_per_frame([off], score=[0.9], first=45),
            one_per_frame([duplicate], score=[0.4]),
            one_per_frame([nowhere], score=[0.97], first=1),
        ]
    )
    return truth, one_per_frame(truth), pred


def test_breakdown_of_a_constructed_scene():
    truth, gt, pred = scene()
    result = breakdown(pred, gt, ious=(0.7, 0.5))
    assert result["group"] == "all" and result["protocol"] == "range"
    matched = result["true_positives"]["all"]
    assert matched["count"] == 45 and matched["flipped"] == 0
    for key in ("median", "mean", "p16", "p84"):
        assert matched["radial_m"][key] == pytest.approx(0.3, abs=1e-6)
        assert matched["tangential_m"][key] == pytest.approx(0.0, abs=1e-6)
        assert matched["yaw_axis_deg"][key] == pytest.approx(0.0, abs=1e-6)
    distance = np.hypot(truth[:45, 0], truth[:45, 1])
    for band, (low, high) in ERROR_BANDS_M.items():
        inside = int(np.sum((distance >= low) & (distance < high)))
        assert result["true_positives"][band]["count"] == inside
    for iou in ("0.7", "0.5"):
        for metric in ("bev", "3d"):
            counts = result["false_positives"][iou][metric]["counts"]["all"]
            assert counts == {"tp": 45, "fp": 3, "fn": 15, "background": 1,
                              "mislocalized": 1, "duplicate": 1, "missed": 14}  # fmt: skip


def test_boxes_facing_backwards_are_counted_not_mixed_into_the_axis_error():
    """12 of the 45 matches turned by 180 deg + 1 deg: they match as well, their axis is 1 deg
    off, and `flipped` counts exactly them."""
    _, gt, pred = scene()
    boxes = pred.boxes.copy()
    boxes[:12, 6] += np.pi + np.radians(1)
    turned = pred.with_columns(yaw=boxes[:, 6])
    matched = breakdown(turned, gt, ious=(0.7,))["true_positives"]["all"]
    assert matched["count"] == 45 and matched["flipped"] == 12
    assert matched["yaw_axis_deg"]["median"] == pytest.approx(0.0, abs=1e-6)
    assert matched["yaw_axis_deg"]["p84"] == pytest.approx(1.0, abs=1e-6)


def test_an_older_breakdown_without_the_axis_error_still_prints():
    """An evaluation written before yaw_axis_deg existed (it had yaw_deg) prints without it."""
    _, gt, pred = scene()
    result = breakdown(pred, gt, ious=(0.7,))
    for band in ERROR_BANDS_M:
        result["true_positives"][band]["yaw_deg"] = result["true_positives"][band].pop(
            "yaw_axis_deg"
        )
    text = format_breakdown(result)
    assert "radial_m" in text and "yaw_axis_deg" not in text and "0 facing backwards" in text


def test_the_ap_each_fix_gains_is_the_ap_of_the_fixed_boxes():
    truth, gt, pred = scene()
    result = breakdown(pred, gt, ious=(0.7,))["false_positives"]["0.7"]["3d"]
    boxes, scores = pred.boxes, np.asarray(pred["score"])
    plain = evaluate(pred, gt)["Car"]["3d"]["all"]
    assert result["ap"] == pytest.approx(plain)
    # mislocalized: the off box snapped onto its car, by hand
    snapped = boxes.copy()
    snapped[45] = truth[45]
    fixed = evaluate(BoxTable.from_arrays(pred.frame_id, snapped, score=scores), gt)
    assert result["ap_fixed"]["mislocalized"] == pytest.approx(fixed["Car"]["3d"]["all"])
    assert result["ap_fixed"]["mislocalized"] > plain
    # the background box (scored above every true one) removed
    keep = np.arange(len(pred)) != 47
    fixed = evaluate(pred.select(keep), gt)["Car"]["3d"]["all"]
    assert result["ap_fixed"]["background"] == pytest.approx(fixed) and fixed > plain
    # the duplicate scores below every true positive: removing it changes nothing
    assert result["ap_fixed"]["duplicate"] == pytest.approx(plain)
    # the 14 cars no box came near, removed from the truth
    fixed = evaluate(pred, gt.select(np.arange(60) < 46))["Car"]["3d"]["all"]
    assert result["ap_fixed"]["missed"] == pytest.approx(fixed) and fixed > plain


def test_a_second_box_on_a_taken_car_is_removed_not_snapped():
    truth = cars_around(50, seed=4, heading_out=True)
    gt = one_per_frame(truth)
    nearby = truth[0].copy()
    nearby[:2] += 1.5 * truth[0, :2] / np.hypot(*truth[0, :2])  # mislocalized on a found car
    pred = BoxTable.concat([one_per_frame(truth, score=np.linspace(0.9, 0.5, 50)),
                            one_per_frame([nearby], score=[0.95])])  # fmt: skip
    result = breakdown(pred, gt)["false_positives"]["0.7"]["bev"]
    assert result["counts"]["all"]["mislocalized"] == 1
    without = evaluate(pred.select(np.arange(51) < 50), gt)["Car"]["bev"]["all"]
    assert result["ap_fixed"]["mislocalized"] == pytest.approx(without)


@pytest.mark.parametrize("seed, iou, crowded", [(20, 0.7, False), (21, 0.5, True)])
def test_kinds_add_up_to_the_evaluators_counts(seed, iou, crowded):
    # random scenes with Vans, other classes, hard and ignored boxes, shared detections
    gt_tables, pred_tables = random_scene(seed, frames=30, crowded=crowded, easy_share=0.5)
    gt, pred = BoxTable.concat(gt_tables), BoxTable.concat(pred_tables)
    for protocol in ("kitti", "range"):
        result = breakdown(pred, gt, ious=(iou,), protocol=protocol)
        metrics = evaluate(pred, gt, iou=iou, protocol=protocol)["Car"]
        for metric in ("bev", "3d"):
            block = result["false_positives"][f"{iou:g}"][metric]
            assert block["ap"] == metrics[metric][result["group"]]
            assert set(block["ap_fixed"]) == set(FIXES)
            for group, counts in block["counts"].items():
                assert {k: counts[k] for k in ("tp", "fp", "fn")} == metrics["counts"][group][
                    metric
                ]
                assert sum(counts[kind] for kind in KINDS) == counts["fp"]
                assert counts["missed"] <= counts["fn"]


def test_ignored_boxes_are_neither_errors_nor_matches():
    cars = cars_around(45, seed=5)
    vans = cars_around(5, seed=6)
    gt = BoxTable.concat(
        [
            one_per_frame(cars),
            BoxTable.from_arrays([f"{k:04d}" for k in range(5)], vans, label="Van"),
        ]
    )
    gt = gt.with_columns(**kitti_columns(50))
    pred = one_per_frame(cars)
    on_vans = BoxTable.from_arrays([f"{k:04d}" for k in range(5)], vans)
    result = breakdown(BoxTable.concat([pred, on_vans]).with_columns(**kitti_columns(50)), gt)
    assert result["protocol"] == "kitti" and result["group"] == "moderate"
    counts = result["false_positives"]["0.7"]["bev"]["counts"]["moderate"]
    assert counts["tp"] == 45 and counts["fp"] == 0  # a car box on a Van is ignored
    assert result["true_positives"]["all"]["count"] == 45


# ---------------------------------------------------------------------------------------------
# The command and the report


def scene_tables(directory):
    """`scene()` written as box tables DIRECTORY/gt and DIRECTORY/pred; returns the predictions."""
    _, gt, pred = scene()
    for name, boxes in (("gt", gt), ("pred", pred)):
        (directory / name).mkdir()
        write_boxes(directory / name, boxes)
    return pred


def test_dali_eval_writes_and_prints_the_breakdown(tmp_path):
    pred = scene_tables(tmp_path)
    out = tmp_path / "metrics.json"
    args = ["eval", "--pred", str(tmp_path / "pred"), "--gt", str(tmp_path / "gt"),
            "--iou", "0.7", "--iou", "0.5", "--out", str(out), "--no-progress"]  # fmt: skip
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "Error breakdown" in result.output and "radial_m" in result.output
    metrics = json.loads(out.read_text())
    errors = metrics["errors"]
    assert set(errors["false_positives"]) == {"0.7", "0.5"}
    assert errors["true_positives"]["all"]["radial_m"]["median"] == pytest.approx(0.3, abs=1e-6)
    for key, iou in (("Car", "0.7"), ("Car@0.5", "0.5")):
        for metric in ("bev", "3d"):
            block = errors["false_positives"][iou][metric]
            assert block["ap"] == metrics[key][metric]["all"]
    # the same breakdown written for a KITTI label directory as predictions
    from dali_cli.importers.kitti_label import write_label_dir

    write_label_dir(tmp_path / "labels", pred)
    again = CliRunner().invoke(main, [*args[:2], str(tmp_path / "labels"), *args[3:-3],
                                      "--out", str(tmp_path / "m2.json")])  # fmt: skip
    assert again.exit_code == 0, again.output
    assert "errors" in json.loads((tmp_path / "m2.json").read_text())


def test_report_shows_the_breakdown_and_names_older_evaluations(tmp_path):
    scene_tables(tmp_path)
    run = tmp_path / "run"
    runner = CliRunner()
    for row in ("iter0/eval", "iter2/eval"):
        args = ["eval", "--pred", str(tmp_path / "pred"), "--gt", str(tmp_path / "gt"),
                "--out", str(run / row)]  # fmt: skip
        assert runner.invoke(main, args).exit_code == 0
    # an evaluation written before the breakdown existed: still up to date, and not an error
    older = run / "iter2" / "eval" / "metrics.json"
    document = json.loads(older.read_text())
    del document["errors"]
    older.write_text(json.dumps(document))
    manifest_path = older.parent / MANIFEST_NAME
    manifest = json.loads(manifest_path.read_text())
    manifest["content_hash"] = hash_tree(older.parent, (MANIFEST_NAME, KITTI_METRICS_NAME))
    manifest_path.write_text(json.dumps(manifest))
    again = runner.invoke(main, [*args, "--no-progress"])
    assert again.exit_code == 0 and "Error breakdown" not in again.output
    assert "errors" not in json.loads(older.read_text())  # skipped: up to date
    report = runner.invoke(main, ["report", str(run)])
    assert report.exit_code == 0, report.output
    text = (run / "report" / "report.md").read_text()
    assert "## Error breakdown" in text and "radial_m" in text
    section = text.split("## Error breakdown")[1].split("\n## ")[0]
    errors_row, losses_row = (line for line in section.splitlines() if "| Source only |" in line)
    assert "| 45 (0 turned > 90°) | +0.30 [+0.30, +0.30] | +0.00 [+0.00, +0.00] |" in errors_row
    # 14 of 60 cars missed outweigh one background and one mislocalized box
    block = json.loads((run / "iter0/eval/metrics.json").read_text())["errors"]
    block = block["false_positives"]["0.7"]["3d"]
    gain = block["ap_fixed"]["missed"] - block["ap"]
    assert losses_row.split("|")[-2].strip() == f"missed (+{gain:.2f})"
    assert "no breakdown: rerun dali eval --force (x2)" in section
    assert (run / "report" / "plots" / "error_breakdown.png").is_file()
    forced = runner.invoke(main, [*args, "--force", "--no-progress"])
    assert forced.exit_code == 0 and "errors" in json.loads(older.read_text())
