"""Test-time augmentation of pseudo-labelling (dali_cli.labels.tta): the mirror, box fusion, and the
stage with a detector whose errors depend on the view: fused labels are closer to the cars and
keep fewer false boxes than one pass, and the manifest records the views."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st
from stub_stage import write_stub_inputs

from dali_cli.cli import main
from dali_cli.geometry import (
    count_points_in_boxes,
    descale_boxes_about_ground,
    scale_boxes_about_ground,
    wrap_angle,
)
from dali_cli.labels.tta import Views, fuse_boxes, mirror_boxes, mirror_points
from dali_cli.store.artifacts import read_boxes

CAR = np.array([10.0, 2.0, -0.9, 3.9, 1.6, 1.5, 0.4])


def test_views_each_and_record():
    views = Views((0.9, 1.0, 1.1), mirror=True)
    assert views.each() == [(0.9, False), (1.0, False), (1.1, False)] + [
        (0.9, True), (1.0, True), (1.1, True)
    ]  # fmt: skip
    assert views.count == 6 and not views.single
    assert Views((1.0,), mirror=False).single and not Views((1.05,), mirror=False).single
    assert views.record() == {
        "scale_factors": [0.9, 1.0, 1.1], "mirror": True, "cluster_iou": 0.5, "views": 6,
    }  # fmt: skip
    for bad in [(), (0.0, 1.0), (1.0, 1.0)]:
        with pytest.raises(ValueError):
            Views(bad)
    with pytest.raises(ValueError):
        Views(cluster_iou=1.0)


@settings(max_examples=40, deadline=None)
@given(
    st.floats(-60, 60), st.floats(-40, 40), st.floats(2, 6), st.floats(1, 2.5),
    st.floats(-np.pi, np.pi - 1e-6),
)  # fmt: skip
def test_mirror_keeps_points_in_their_box_and_is_its_own_inverse(x, y, length, w, yaw):
    box = np.array([[x, y, -1.0, length, w, 1.5, yaw]])
    rng = np.random.default_rng(0)
    local = rng.uniform(-0.49, 0.49, (50, 3)) * box[0, 3:6]
    c, s = np.cos(yaw), np.sin(yaw)
    xyz = np.stack(
        [c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1], local[:, 2]], 1
    )
    points = np.c_[xyz + box[0, :3], np.full(50, 0.2)].astype(np.float32)
    assert count_points_in_boxes(points, box)[0] == 50
    assert count_points_in_boxes(mirror_points(points), mirror_boxes(box))[0] == 50
    back = mirror_boxes(mirror_boxes(box))
    assert np.allclose(back[:, :6], box[:, :6])
    assert abs(wrap_angle(back[0, 6] - box[0, 6])) < 1e-9
    assert np.array_equal(mirror_points(points)[:, [0, 2, 3]], points[:, [0, 2, 3]])


def test_fusion_of_agreeing_views_keeps_the_box_and_its_score():
    boxes = np.repeat(CAR[None], 4, axis=0)
    fused, scores, support = fuse_boxes(boxes, np.full(4, 0.8), np.arange(4), 4, 0.5)
    assert np.allclose(fused, CAR[None]) and scores == pytest.approx([0.8]) and support[0] == 4


def test_fusion_is_the_score_weighted_mean_and_a_lone_box_keeps_a_fraction():
    shifted = np.array([CAR, CAR + [0.3, 0, 0, 0, 0, 0, 0], CAR + [0, -0.1, 0, 0.2, 0, 0, 0.04]])
    lone = CAR + [0, 20.0, 0, 0, 0, 0, 0]  # another place: only view 2 sees it
    weights = np.array([0.9, 0.6, 0.3])
    fused, scores, support = fuse_boxes(
        np.r_[shifted, lone[None]], np.r_[weights, 0.9], np.array([0, 1, 2, 2]), 3, 0.5
    )
    order = np.argsort(fused[:, 1])
    fused, scores, support = fused[order], scores[order], support[order]
    assert np.allclose(fused[0, :6], weights @ shifted[:, :6] / weights.sum())
    assert fused[0, 6] == pytest.approx(CAR[6] + 0.3 * 0.04 / weights.sum())
    assert scores[0] == pytest.approx(weights.sum() / 3) and support[0] == 3
    assert np.allclose(fused[1], lone) and scores[1] == pytest.approx(0.3) and support[1] == 1


def test_each_view_contributes_its_best_box_only():
    """A view's near-duplicate does not count twice: score and position come from its best."""
    duplicate = CAR + [0.4, 0, 0, 0, 0, 0, 0]
    fused, scores, support = fuse_boxes(
        np.stack([CAR, duplicate, CAR]), np.array([0.9, 0.8, 0.9]), np.array([0, 0, 1]), 2, 0.5
    )
    assert len(fused) == 1 and support[0] == 2
    assert scores[0] == pytest.approx(0.9) and np.allclose(fused[0], CAR)


def test_a_reversed_twin_fuses_to_the_leaders_heading_not_a_sideways_box():
    twin = CAR.copy()
    twin[6] = wrap_angle(CAR[6] + np.pi + 0.02)
    fused, _, _ = fuse_boxes(np.stack([CAR, twin]), np.array([0.9, 0.9]), np.array([0, 1]), 2, 0.5)
    assert len(fused) == 1 and fused[0, 6] == pytest.approx(CAR[6] + 0.01)


def test_separate_cars_are_not_merged_and_empty_input_is_empty():
    other = CAR + [0, 3.0, 0, 0, 0, 0, 0]  # side by side, no overlap
    fused, _, support = fuse_boxes(
        np.stack([CAR, other] * 2), np.full(4, 0.7), np.array([0, 0, 1, 1]), 2, 0.5
    )
    assert len(fused) == 2 and list(support) == [2, 2]
    fused, scores, support = fuse_boxes(np.zeros((0, 7)), np.zeros(0), np.zeros(0), 10, 0.5)
    assert fused.shape == (0, 7) and scores.shape == (0,) and support.shape == (0,)


# ---------------------------------------------------------------------------------------------
# the stage

MOUNT = 1.73
LWH = np.array([3.89, 1.62, 1.53])


def cars(frame: int) -> np.ndarray:
    """Three cars on the ground, left and right of the sensor (sensor frame, (3, 7))."""
    boxes = np.zeros((3, 7))
    boxes[:, 0] = [8.0, 18.0, 30.0]
    boxes[:, 1] = [3.0, -4.0, 6.0]
    boxes[:, 2] = -MOUNT + LWH[2] / 2
    boxes[:, 3:6] = LWH
    boxes[:, 6] = [0.2 * frame, -0.5, 1.0]
    return boxes


def frame_points(frame: int) -> np.ndarray:
    """Points in each car; the first point (in car 0, at y = +3 m) tells the detector the frame
    (intensity) and whether the cloud is mirrored (its y)."""
    rng = np.random.default_rng(frame)
    clouds = []
    for box in cars(frame):
        local = rng.uniform(-0.45, 0.45, (40, 3)) * box[3:6]
        c, s = np.cos(box[6]), np.sin(box[6])
        xy = np.stack([c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1]], 1)
        clouds.append(np.c_[xy + box[:2], local[:, 2] + box[2]])
    xyz = np.concatenate(clouds)
    intensity = np.full((len(xyz), 1), 0.3)
    intensity[0] = frame / 100.0
    return np.c_[xyz, intensity].astype(np.float32)


class ViewNoiseDetector:
    """Finds every car in the scaled cloud, but each view misplaces it along x by a
    view-dependent offset (2 x the scale factor's deviation from 1, in m, -/+ 5 cm unmirrored /
    mirrored: zero on average over symmetric factors and both mirrors) and adds, in the unmirrored view at the
    factor 1 only, a false car 25 m to the side with score 0.8."""

    def __init__(self, scale: float):
        self.base_scale = scale
        self.calls: list[tuple[float, bool]] = []

    def predict(self, points_list, scale=1.0, mount_height_m=None):
        results = []
        for points in points_list:
            frame = int(round(float(points[0, 3]) * 100))
            mirrored = bool(points[0, 1] < 0)
            self.calls.append((round(scale / self.base_scale, 6), mirrored))
            boxes = cars(frame)
            factor = scale / self.base_scale
            boxes[:, 0] += 2.0 * (factor - 1.0) + (0.05 if mirrored else -0.05)
            scores = np.full(len(boxes), 0.9, np.float32)
            if factor == pytest.approx(1.0) and not mirrored:
                false = boxes[:1].copy()
                false[:, 1] += 25.0
                boxes, scores = np.r_[boxes, false], np.r_[scores, np.float32(0.8)]
            if mirrored:
                boxes = mirror_boxes(boxes)
            scaled = scale_boxes_about_ground(boxes, scale, mount_height_m)
            results.append((descale_boxes_about_ground(scaled, scale, mount_height_m), scores))
        return results


@pytest.fixture
def stage(tmp_path, monkeypatch):
    target, model = write_stub_inputs(tmp_path, [frame_points(i) for i in range(4)])
    detector = ViewNoiseDetector(1.2)
    import stages.pseudo_label

    monkeypatch.setattr(stages.pseudo_label, "load_detector", lambda _: detector)
    return tmp_path, target, model, detector


def label(model, target, out, *options):
    # the fusion checked alone: the point fit (on by default) would move the stub boxes
    return CliRunner().invoke(
        main,
        ["pseudo-label", "--model", str(model), "--target", str(target), "--scale", "1.2",
         "--out", str(out), "--no-progress", "--no-fit-points", *options],
    )  # fmt: skip


def errors_and_count(out) -> tuple[float, int]:
    table = read_boxes(out)
    truth = {f"{i:03d}": cars(i) for i in range(4)}
    worst = 0.0
    for frame_id, rows in table.rows_by_frame().items():
        for box in table.boxes[rows]:
            worst = max(worst, float(np.min(np.hypot(*(truth[frame_id][:, :2] - box[:2]).T))))
    return worst, len(table)


def test_fused_labels_sit_on_the_cars_and_drop_a_one_view_false_box(stage):
    tmp_path, target, model, detector = stage
    single, fused = tmp_path / "single", tmp_path / "fused"
    result = label(model, target, single)  # the default: one pass
    assert result.exit_code == 0, result.output
    error_single, count_single = errors_and_count(single)
    assert count_single == 4 * 4 and error_single > 20  # the false car is kept
    detector.calls.clear()
    result = label(model, target, fused, "--tta", "--tta-scales", "0.9,1,1.1")
    assert result.exit_code == 0, result.output
    assert sorted(set(detector.calls)) == [
        (0.9, False), (0.9, True), (1.0, False), (1.0, True), (1.1, False), (1.1, True)
    ]  # fmt: skip
    error_fused, count_fused = errors_and_count(fused)
    assert count_fused == 4 * 3  # score 0.8 / 6 views: under the cut
    assert error_fused < 1e-6  # the view offsets cancel
    manifest = json.loads((fused / "manifest.json").read_text())
    assert manifest["params"]["tta"] == {
        "scale_factors": [0.9, 1.0, 1.1], "mirror": True, "cluster_iou": 0.5, "views": 6,
    }  # fmt: skip
    assert "tta" not in json.loads((single / "manifest.json").read_text())["params"]


def test_tta_options_change_the_labels_identity_and_bad_factors_are_refused(stage):
    tmp_path, target, model, _ = stage
    out = tmp_path / "p"
    single = label(model, target, out, "--tta", "--tta-scales", "1", "--no-tta-mirror")
    assert single.exit_code == 0, single.output
    again = label(model, target, out)  # the default, the same single view: up to date
    assert again.exit_code == 0 and "up to date" in again.output
    rerun = label(model, target, out, "--tta")  # ten views: a different artifact, rebuilt
    assert rerun.exit_code == 0 and "up to date" not in rerun.output
    without = label(model, target, tmp_path / "bad", "--tta-scales", "0.9,1.1")
    assert without.exit_code == 2 and "--tta-scales needs --tta" in without.output
    for bad in ["0.9,x", "0,1", "1,1"]:
        result = label(model, target, tmp_path / "bad", "--tta", "--tta-scales", bad)
        assert result.exit_code == 2 and "--tta-scales" in result.output
        assert not (tmp_path / "bad").exists()
