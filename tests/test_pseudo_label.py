"""`dali pseudo-label` with stub detectors: score cut, BEV NMS, in-box point counts on the original
points, the scale read from a PTSN sweep, and the PTSN scaling round trip it relies on."""

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
    descale_boxes_about_ground,
    scale_boxes_about_ground,
    scale_points_about_ground,
)
from dali_cli.store.artifacts import read_boxes
from dali_cli.store.scale_file import read_scale

KITTI_LWH = np.array([3.89, 1.62, 1.53])
MOUNT = 1.73  # the kitti profile's mount height
PER_BOX = 40


def car_boxes(frame: int) -> np.ndarray:
    """Two or three KITTI-sized cars standing on the ground, sensor frame, (K, 7)."""
    count = 2 + frame % 2
    boxes = np.zeros((count, 7))
    boxes[:, 0] = 8.0 + 9.0 * np.arange(count)
    boxes[:, 1] = (-1.0) ** np.arange(count) * 3.0
    boxes[:, 2] = -MOUNT + KITTI_LWH[2] / 2
    boxes[:, 3:6] = KITTI_LWH
    boxes[:, 6] = 0.3 * frame - 1.0
    return boxes


def frame_points(frame: int) -> np.ndarray:
    """PER_BOX points inside each car plus ground points away from them, (n, 4) float32.
    The first point's intensity encodes the frame index for the stub detector."""
    rng = np.random.default_rng(frame)
    clouds = []
    for box in car_boxes(frame):
        local = rng.uniform(-0.45, 0.45, size=(PER_BOX, 3)) * box[3:6]
        c, s = np.cos(box[6]), np.sin(box[6])
        rotated = np.stack(
            [c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1], local[:, 2]], 1
        )
        clouds.append(rotated + box[:3])
    ground = np.stack(
        [rng.uniform(-30, -5, 200), rng.uniform(-20, 20, 200), np.full(200, -MOUNT)], 1
    )
    xyz = np.concatenate([*clouds, ground])
    intensity = np.full((len(xyz), 1), 0.3)
    intensity[0] = frame / 100.0
    return np.concatenate([xyz, intensity], axis=1).astype(np.float32)


class SizeLawDetector:
    """In the s-scaled cloud it finds each car at its scaled centre but with size `scaled_lwh`
    (its training bias), standing on the ground; boxes come back de-scaled, so their size is
    scaled_lwh / s. Per frame it adds a near-duplicate (score 0.5) and a faint box (score 0.1)."""

    def __init__(self, scaled_lwh=KITTI_LWH):
        self.scaled_lwh = np.asarray(scaled_lwh, np.float64)
        self.scales: list[float] = []

    def predict(self, points_list, scale=1.0, mount_height_m=None):
        self.scales.append(scale)
        results = []
        for points in points_list:
            frame = int(round(float(points[0, 3]) * 100))
            cars = car_boxes(frame)
            scaled = scale_boxes_about_ground(cars, scale, mount_height_m)
            scaled[:, 3:6] = self.scaled_lwh
            scaled[:, 2] = -mount_height_m + self.scaled_lwh[2] / 2
            duplicate, faint = scaled[:1].copy(), scaled[:1].copy()
            duplicate[:, 0] += 0.2
            faint[:, 1] += 10.0
            boxes = np.concatenate([scaled, duplicate, faint])
            scores = np.r_[np.full(len(scaled), 0.9), 0.5, 0.1].astype(np.float32)
            results.append((descale_boxes_about_ground(boxes, scale, mount_height_m), scores))
        return results


@pytest.fixture
def setup(tmp_path, monkeypatch):
    target, model = write_stub_inputs(tmp_path, [frame_points(i) for i in range(6)])
    detector = SizeLawDetector(KITTI_LWH * 1.2)
    import stages.pseudo_label
    import stages.ptsn_sweep

    monkeypatch.setattr(stages.pseudo_label, "load_detector", lambda _: detector)
    monkeypatch.setattr(stages.ptsn_sweep, "load_detector", lambda _: detector)
    return tmp_path, target, model, detector


def run(*arguments):
    return CliRunner().invoke(main, [*map(str, arguments)])


def PSEUDO_LABEL(model, target):  # noqa: N802 (reads as the command line it starts)
    # the point fit (on by default, tests/test_box_fit.py) would move these stub boxes off the
    # uniform points they hold: these tests check the scale, cut, NMS and count exactly
    return ("pseudo-label", "--model", model, "--data", target, "--no-fit-points")


def test_pseudo_labels_at_the_swept_scale_match_e_est(setup):
    tmp_path, target, model, detector = setup
    ptsn_dir, out = tmp_path / "ptsn", tmp_path / "pseudo"
    result = run(
        "ptsn-sweep", "--model", model, "--data", target, "--out", ptsn_dir, "--no-progress"
    )
    assert result.exit_code == 0, result.output
    scale = json.loads((ptsn_dir / "scale.json").read_text())["scale"]
    assert scale == pytest.approx(1.2, abs=2e-3)
    detector.scales.clear()
    result = run(
        *PSEUDO_LABEL(model, target),
        "--scale-from",
        ptsn_dir,
        "--out",
        out,
        "--no-progress",
    )
    assert result.exit_code == 0, result.output
    assert set(detector.scales) == {scale}  # one pass
    table = read_boxes(out)
    expected_boxes = sum(len(car_boxes(i)) for i in range(6))
    assert len(table) == expected_boxes  # the duplicate (NMS) and the faint box (score) are gone
    assert np.all(table["score"] >= 0.3) and "scale" not in table.columns
    assert read_scale(out).scale == scale  # ŝ stored once: OUT/scale.json, exactly as found
    assert np.all(table["num_points"] == PER_BOX)  # counted on the original (unscaled) points
    summary = json.loads((out / "summary.json").read_text())
    assert np.abs(np.asarray(summary["mean_minus_E_est"])).max() < 0.01  # within 0.1 m required
    assert summary["boxes"] == expected_boxes and summary["frames"] == 6
    assert sum(summary["score_histogram"]["counts"]) == expected_boxes
    truth = np.concatenate([car_boxes(i) for i in range(6)])
    order = np.lexsort((table.boxes[:, 0], table.frame_id.astype(str)))
    assert np.allclose(table.boxes[order][:, [0, 1, 6]], truth[:, [0, 1, 6]], atol=1e-6)
    assert np.allclose(table.boxes[order][:, 2], truth[:, 2], atol=0.01)  # same ground plane


def test_explicit_scale_overrides_and_options(setup):
    tmp_path, target, model, detector = setup
    out = tmp_path / "p1"
    result = run(
        "pseudo-label", "--model", model, "--data", target, "--scale", "1.0", "--out", out,
        "--no-progress", "--nms-iou", "0.95", "--score-min", "0.05",
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert detector.scales == [1.0]  # one detector pass (one batch)
    table = read_boxes(out)
    assert len(table) == sum(len(car_boxes(i)) + 2 for i in range(6))  # nothing suppressed
    assert np.allclose(table.boxes[table["score"] > 0.8][:, 3:6], KITTI_LWH * 1.2)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["E_est"] is None and summary["scale_source"] == "option"


def test_missing_scale_is_a_usage_error(setup):
    tmp_path, target, model, _ = setup
    result = run("pseudo-label", "--model", model, "--data", target, "--out", tmp_path / "x")
    assert result.exit_code == 2 and "--scale-from" in result.output
    bad = tmp_path / "bad_ptsn"
    bad.mkdir()
    (bad / "scale.json").write_text(json.dumps({"scale": -1}))
    result = run(
        *PSEUDO_LABEL(model, target),
        "--scale-from",
        bad,
        "--out",
        tmp_path / "y",
    )
    assert result.exit_code == 1 and "scale.json" in result.output and "'scale'" in result.output
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


# ---------------------------------------------------------------------------------------------
# the scaling PTSN relies on (dali_cli.geometry)

finite = st.floats(-80, 80, allow_nan=False)
boxes_strategy = st.lists(
    st.tuples(
        finite,
        finite,
        st.floats(-3, 3),
        st.floats(0.1, 8),
        st.floats(0.1, 3),
        st.floats(0.1, 3),
        st.floats(-3.14, 3.14),
    ),
    min_size=1,
    max_size=8,
)


@settings(max_examples=60, deadline=None)
@given(boxes_strategy, st.floats(0.5, 2.0), st.floats(0.0, 2.5))
def test_scale_then_descale_is_identity(boxes, scale, mount):
    boxes = np.asarray(boxes)
    back = descale_boxes_about_ground(scale_boxes_about_ground(boxes, scale, mount), scale, mount)
    assert np.abs(back - boxes).max() <= 1e-9
    scaled = scale_boxes_about_ground(boxes, scale, mount)
    assert np.array_equal(scaled[:, 6], boxes[:, 6])  # yaw kept
    assert np.allclose(scaled[:, 3:6], boxes[:, 3:6] * scale)


@settings(max_examples=40, deadline=None)
@given(st.floats(0.5, 2.0), st.floats(0.0, 2.5))
def test_ground_scaling_keeps_the_ground_plane(scale, mount):
    rng = np.random.default_rng(0)
    points = rng.uniform(-50, 50, size=(100, 4)).astype(np.float32)
    points[:50, 2] = -mount  # on the ground
    scaled = scale_points_about_ground(points, scale, mount)
    assert np.allclose(scaled[:50, 2], -mount, atol=1e-5)
    assert np.array_equal(scaled[:, 3], points[:, 3])  # intensity untouched
    height = points[50:, 2] + mount
    assert np.allclose(scaled[50:, 2] + mount, height * scale, atol=1e-4)


class AbsurdBoxDetector(SizeLawDetector):
    """SizeLawDetector plus, per frame, a 1,000 km long box over the first car and a box 1,000 km
    away, both scored above every car, and one absurd box below the score cut."""

    def predict(self, points_list, scale=1.0, mount_height_m=None):
        results = []
        for boxes, scores in super().predict(points_list, scale, mount_height_m):
            huge, far, faint = boxes[:1].copy(), boxes[:1].copy(), boxes[:1].copy()
            huge[:, 3] = 1e6
            far[:, 0] = 1e6
            faint[:, 4] = 1e30
            boxes = np.concatenate([huge, far, faint, boxes])
            results.append((boxes, np.r_[0.99, 0.99, 0.1, scores].astype(np.float32)))
        return results


def test_implausible_detections_are_dropped_before_nms_and_counted(setup, monkeypatch):
    """Dropped before NMS, counted."""
    tmp_path, target, model, _ = setup
    import stages.pseudo_label

    monkeypatch.setattr(stages.pseudo_label, "load_detector", lambda _: AbsurdBoxDetector())
    out = tmp_path / "pseudo"
    result = run(
        "pseudo-label", "--model", model, "--data", target, "--scale", "1.0", "--out", out,
        "--no-progress",
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    implausible = 12  # two per frame
    assert "WARNING" in result.output and f"{implausible} implausible" in result.output
    table = read_boxes(out)
    # every car survives: the 1,000 km box (score 0.99) did not suppress the first one in NMS
    assert len(table) == sum(len(car_boxes(i)) for i in range(6))
    assert table.boxes[:, 3].max() < 10 and np.abs(table.boxes[:, 0]).max() < 100
    manifest = json.loads((out / "manifest.json").read_text())
    counted = manifest["outputs"]["counts"]["boxes_implausible"]
    assert counted == implausible  # the faint one is not counted
    assert json.loads((out / "summary.json").read_text())["boxes_implausible"] == implausible


WAYMO_OVER_KITTI = np.array([1.20, 1.29, 1.14])  # per-dimension source/target size ratios


def test_size_correction_removes_an_anisotropic_bias(setup, monkeypatch):
    """A detector biased like Waymo -> KITTI (l x1.20, w x1.29, h x1.14): the volume-matched ŝ
    leaves a per-dimension bias; the default correction brings each mean within 1 cm of E_est,
    cars keep standing on the ground, and `--size-correction none` keeps the bias."""
    tmp_path, target, model, _ = setup
    import stages.pseudo_label
    import stages.ptsn_sweep

    biased = SizeLawDetector(KITTI_LWH * WAYMO_OVER_KITTI)
    monkeypatch.setattr(stages.pseudo_label, "load_detector", lambda _: biased)
    monkeypatch.setattr(stages.ptsn_sweep, "load_detector", lambda _: biased)
    ptsn_dir = tmp_path / "ptsn-aniso"
    result = run("ptsn-sweep", "--model", model, "--data", target, "--out", ptsn_dir,
                 "--no-progress")  # fmt: skip
    assert result.exit_code == 0, result.output
    e_est = np.asarray(json.loads((ptsn_dir / "scale.json").read_text())["E_est"])
    # positions are checked exactly below: no point fit
    base = ["pseudo-label", "--model", model, "--data", target, "--scale-from", ptsn_dir,
            "--no-progress", "--no-fit-points"]  # fmt: skip

    assert run(*base, "--out", tmp_path / "raw", "--size-correction", "none").exit_code == 0
    raw = read_boxes(tmp_path / "raw")
    assert np.abs(raw.boxes[:, 3:6].mean(axis=0) - e_est).max() > 0.05  # the bias to remove

    result = run(*base, "--out", tmp_path / "fixed")
    assert result.exit_code == 0, result.output
    fixed = read_boxes(tmp_path / "fixed")
    assert np.abs(fixed.boxes[:, 3:6].mean(axis=0) - e_est).max() < 0.01
    bottoms = fixed.boxes[:, 2] - fixed.boxes[:, 5] / 2
    assert np.allclose(bottoms, raw.boxes[:, 2] - raw.boxes[:, 5] / 2, atol=1e-9)
    assert np.allclose(fixed.boxes[:, [0, 1, 6]], raw.boxes[:, [0, 1, 6]])
    assert np.all(fixed["num_points"] == PER_BOX)  # recounted: the boxes still hold their car
    record = json.loads((tmp_path / "fixed" / "manifest.json").read_text())["size_correction"]
    assert record["method"] == "per-dim"
    assert np.allclose(record["factors_lwh"], e_est / raw.boxes[:, 3:6].mean(axis=0), atol=1e-4)
    assert np.allclose(record["mean_lwh_after"], e_est, atol=1e-4)
    summary = json.loads((tmp_path / "fixed" / "summary.json").read_text())
    assert np.abs(np.asarray(summary["mean_minus_E_est"])).max() < 0.01


def test_correct_sizes_matches_e_est_per_frame_and_pooled():
    from dali_cli.labels.size_correction import correct_sizes

    rng = np.random.default_rng(5)
    n = 200
    boxes = np.zeros((n, 7))
    boxes[:, :2] = rng.uniform(-30, 30, (n, 2))
    boxes[:, 3:6] = KITTI_LWH * [1.03, 1.08, 0.95] * rng.normal(1, 0.05, (n, 3))
    boxes[:, 2] = -MOUNT + boxes[:, 5] / 2
    boxes[:, 6] = rng.uniform(-np.pi, np.pi, n)
    scores = rng.uniform(0, 1, n)
    frames = rng.integers(0, 17, n).astype(str)
    for mean in ("per-frame", "pooled"):
        fixed, record = correct_sizes(boxes, scores, frames, KITTI_LWH, score_min=0.3, mean=mean)
        used = scores >= 0.3
        if mean == "pooled":
            assert np.abs(fixed[used, 3:6].mean(axis=0) - KITTI_LWH).max() < 1e-9
        else:  # mean of the frames' means, computed here independently
            per_frame = [
                fixed[used & (frames == f), 3:6].mean(axis=0) for f in np.unique(frames[used])
            ]
            assert np.abs(np.mean(per_frame, axis=0) - KITTI_LWH).max() < 1e-9
        assert np.allclose(fixed[:, 2] - fixed[:, 5] / 2, -MOUNT)  # bottoms stay on the ground
        assert np.allclose(record.mean_after, KITTI_LWH)
    _, unchanged = correct_sizes(boxes, scores, frames, KITTI_LWH, method="none")
    assert np.allclose(unchanged.factors, 1.0)
    with pytest.raises(ValueError):
        correct_sizes(boxes, scores, frames, [3.9, -1.0, 1.5])
