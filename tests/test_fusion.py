"""Test-time fusion (dali_cli/detector/fusion.py): weighted box fusion of rotated boxes, the
heading vote, the mirror pass, and the detect / eval options that turn it on."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from dali_cli.cli import main
from dali_cli.detector.fusion import (
    TestTimeFusion,
    fuse_boxes,
    mirror_boxes,
    mirror_points,
    vote_heading,
)
from dali_cli.geometry import bev_iou, count_points_in_boxes, wrap_angle

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "kitti-hdl64e"
SCAN = ROOT / "tests" / "fixtures" / "real" / "kitti" / "training" / "velodyne" / "000008.bin"

box_st = st.tuples(
    st.floats(-60, 60), st.floats(-40, 40), st.floats(-2, 1),
    st.floats(2.5, 6), st.floats(1.2, 2.2), st.floats(1.2, 2.0), st.floats(-np.pi, np.pi),
)  # fmt: skip


def angle_gap(a, b):
    return np.abs(wrap_angle(np.asarray(a) - np.asarray(b)))


@given(box=box_st, scores=st.lists(st.floats(0, 1), min_size=1, max_size=6),
       passes=st.integers(1, 6))  # fmt: skip
@settings(max_examples=60, deadline=None)
def test_fusing_copies_of_one_box_gives_that_box(box, scores, passes):
    boxes = np.tile(np.asarray(box, float), (len(scores), 1))
    fused, fused_scores = fuse_boxes(boxes, scores, passes)
    assert fused.shape == (1, 7)
    np.testing.assert_allclose(fused[0, :6], box[:6], atol=1e-9)
    assert angle_gap(fused[0, 6], box[6]) < 1e-9
    expected = np.mean(scores) * min(len(scores), passes) / passes
    assert fused_scores[0] == pytest.approx(expected, abs=1e-6)


def test_the_vote_keeps_the_majority_direction_where_the_angle_mean_points_sideways():
    """Two members face +x (yaw ~0), a stronger one faces -x: the score-weighted mean of the
    angles (about 1.5 rad) would turn the car sideways; the vote keeps the axis, facing +x."""
    yaws = np.array([0.1, 0.05, np.pi - 0.05])
    weights = np.array([0.5, 0.5, 0.9])
    assert angle_gap(np.average(yaws, weights=weights), np.pi / 2) < 0.2  # the naive mean
    boxes = np.array([[10.0, 2.0, -1.0, 4.0, 1.7, 1.5, yaw] for yaw in yaws])
    fused, _ = fuse_boxes(boxes, weights, passes=3)
    assert len(fused) == 1 and angle_gap(fused[0, 6], 0.05) < 0.1
    # the weights decide: made heavier, the rear-facing member wins
    fused, _ = fuse_boxes(boxes, np.array([0.3, 0.3, 0.9]), passes=3)
    assert angle_gap(fused[0, 6], np.pi - 0.05) < 0.1


def test_a_tied_vote_goes_to_the_seed():
    cluster = np.zeros(2, np.int64)
    for seed in (0.0, np.pi):
        yaw = vote_heading(np.array([0.0, np.pi]), np.ones(2), cluster, np.array([seed]))
        assert angle_gap(yaw[0], seed) < 1e-9


@given(
    boxes=st.lists(box_st, min_size=0, max_size=25),
    scores=st.lists(st.floats(0, 1), min_size=25, max_size=25),
    passes=st.integers(1, 6),
    iou=st.floats(0.1, 0.9),
)
@settings(max_examples=60, deadline=None)
def test_fused_scores_lie_in_0_1_and_no_box_is_lost(boxes, scores, passes, iou):
    boxes = np.asarray(boxes, float).reshape(-1, 7)
    scores = np.asarray(scores[: len(boxes)])
    fused, fused_scores = fuse_boxes(boxes, scores, passes, iou)
    assert len(fused) == len(fused_scores) <= len(boxes)
    assert ((fused_scores >= 0) & (fused_scores <= 1)).all()
    assert (np.diff(fused_scores) <= 0).all()
    if len(boxes):  # every input box lies near some fused box: none vanishes in a cluster
        near = np.hypot(*(boxes[:, None, :2] - fused[None, :, :2]).transpose(2, 0, 1)).min(1)
        assert (near <= np.hypot(boxes[:, 3], boxes[:, 4])).all()


def test_boxes_below_the_iou_threshold_stay_apart_and_a_lone_box_is_demoted():
    boxes = np.array([[10.0, 0, -1, 4, 1.7, 1.5, 0], [10.0, 5, -1, 4, 1.7, 1.5, 0]])
    fused, scores = fuse_boxes(boxes, [0.8, 0.6], passes=2)
    assert len(fused) == 2
    np.testing.assert_allclose(scores, [0.4, 0.3], atol=1e-6)


@given(box=box_st, seed=st.integers(0, 2**16))
@settings(max_examples=40, deadline=None)
def test_a_mirrored_box_holds_the_mirrored_points(box, seed):
    """mirror_boxes is its own inverse and keeps which points lie in a box: a yaw left
    unmirrored (or mirrored the wrong way) would move the box off its points."""
    box = np.asarray([box], float)
    rng = np.random.default_rng(seed)
    points = np.c_[box[0, :3] + rng.uniform(-3, 3, (400, 3)), np.zeros(400)]
    np.testing.assert_allclose(mirror_boxes(mirror_boxes(box)), box, atol=1e-12)
    inside = count_points_in_boxes(points, box)
    assert (count_points_in_boxes(mirror_points(points), mirror_boxes(box)) == inside).all()


@pytest.fixture(scope="module")
def shipped():
    if not SCAN.is_file():
        pytest.skip("KITTI fixture not found")
    from dali_cli.detector import Detector
    from dali_cli.store.scale_file import read_scale

    points = np.fromfile(SCAN, "<f4").reshape(-1, 4)
    return Detector.load(MODEL), read_scale(MODEL).scale, points


def test_the_mirror_pass_of_the_shipped_model_comes_back_onto_the_scans_cars(shipped):
    """On a real KITTI scan, the shipped model's boxes on the mirror image, mirrored back, lie
    on its confident boxes of the scan itself (BEV IoU > 0.5 for most of them: the network is
    not exactly mirror-symmetric); left unmirrored, they lie on almost none."""
    detector, scale, points = shipped
    ((direct, direct_scores),) = detector.predict([points], scale, 1.73)
    ((mirrored, mirrored_scores),) = detector.predict([mirror_points(points)], scale, 1.73)
    direct, mirrored = direct[direct_scores >= 0.5], mirrored[mirrored_scores >= 0.1]
    assert len(direct) >= 3 and len(mirrored) >= 3
    assert (bev_iou(direct, mirror_boxes(mirrored)).max(axis=1) > 0.5).mean() >= 0.75
    assert (bev_iou(direct, mirrored).max(axis=1) > 0.5).mean() <= 0.25


def test_flip_fusion_of_the_mirror_image_is_the_mirror_of_flip_fusion(shipped):
    """Fusing the scan with its mirror image is symmetric: on the mirrored scan it gives the
    same boxes mirrored (the same two clouds go through the network)."""
    detector, scale, points = shipped
    fusion = TestTimeFusion(flip=True)
    ((boxes, scores),) = fusion.predict(detector, [points], scale, 1.73)
    ((other, other_scores),) = fusion.predict(detector, [mirror_points(points)], scale, 1.73)
    assert len(boxes) == len(other) > 0
    np.testing.assert_allclose(other_scores, scores, atol=1e-6)
    np.testing.assert_allclose(mirror_boxes(other)[:, :6], boxes[:, :6], atol=1e-6)
    assert (angle_gap(mirror_boxes(other)[:, 6], boxes[:, 6]) < 1e-6).all()


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_detect_records_the_fusion_and_eval_refuses_it_without_a_model(tmp_path):
    if not SCAN.is_file():
        pytest.skip("KITTI fixture not found")
    scans = tmp_path / "scans"
    scans.mkdir()
    shutil.copy(SCAN, scans / "000008.bin")
    out = tmp_path / "fused"
    result = invoke("detect", scans, "--model", MODEL, "--tta-flip", "--tta-scales",
                    "0.95,1", "--no-progress", "--out", out)  # fmt: skip
    assert result.exit_code == 0, result.output
    params = json.loads((out / "manifest.json").read_text())["params"]
    assert params["test_time_fusion"] == {"flip": True, "scale_factors": [0.95, 1.0], "iou": 0.55}
    result = invoke("eval", "--pred", out, "--gt", out, "--tta-flip")
    assert result.exit_code == 2 and "--model" in result.output
    result = invoke("detect", scans, "--model", MODEL, "--tta-scales", "1,0.9", "--out", out)
    assert result.exit_code == 2 and "increasing" in result.output
