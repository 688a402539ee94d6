"""The virtual KITTI camera: 2D boxes, truncation, occlusion levels, and the kitti protocol on
labels that carry them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dali_cli.evaluation.evaluate import evaluate
from dali_cli.importers import camera
from dali_cli.importers.kitti import read_calib
from dali_cli.store.artifacts import BoxTable

CALIB_FIXTURE = Path(__file__).parent / "fixtures/real/kitti/training/calib/000008.txt"
CAR = (3.9, 1.6, 1.5)  # l, w, h in metres


def cars(xy, yaw=0.0, z=-0.95) -> np.ndarray:
    """`(N, 7)` KITTI-sized cars standing on the ground (LiDAR 1.73 m up) at `xy` `(N, 2)`."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    count = len(xy)
    return np.c_[xy, np.full(count, z), np.tile(CAR, (count, 1)), np.broadcast_to(yaw, count)]


def height_px(boxes) -> np.ndarray:
    columns = camera.kitti_label_columns(boxes, np.zeros(len(boxes)))
    return columns["bbox_bottom"] - columns["bbox_top"]


def test_nominal_camera_is_the_real_kitti_calib():
    real = read_calib(CALIB_FIXTURE)
    for name in ("P2", "R0_rect", "Tr_velo_to_cam"):
        np.testing.assert_allclose(getattr(camera.NOMINAL_CALIB, name), getattr(real, name))
    # the camera sits about 0.27 m in front of the LiDAR
    origin = camera.NOMINAL_CALIB.rect_to_lidar(np.zeros((1, 3)))[0]
    assert origin[0] == pytest.approx(0.27, abs=0.01) and abs(origin[1]) < 0.02


def test_car_ahead_is_centred_and_shrinks_with_distance():
    boxes = cars([[10.0, 0.0], [40.0, 0.0], [80.0, 0.0]])
    columns = camera.kitti_label_columns(boxes, np.zeros(3))
    centre = (columns["bbox_left"] + columns["bbox_right"]) / 2
    np.testing.assert_allclose(centre, camera.KITTI_P2[0, 2], atol=8.0)  # P2's 6 cm offset
    height = columns["bbox_bottom"] - columns["bbox_top"]
    # the near face sets the height: (40 - l/2) / (10 - l/2) ~ 4.7
    assert 4.0 < height[0] / height[1] < 5.5
    assert height[2] < 25.0 < height[1]  # moderate ignores the 80 m car, keeps the 40 m one
    np.testing.assert_array_equal(columns["truncated"], 0.0)
    # alpha of a car driving away straight ahead is -pi/2 (KITTI's convention)
    np.testing.assert_allclose(columns["alpha"], -np.pi / 2, atol=0.02)


def test_cars_behind_or_beside_are_fully_truncated():
    boxes = cars([[-10.0, 0.0], [0.0, 6.0], [2.0, -10.0], [-2.5, 0.0]])
    columns = camera.kitti_label_columns(boxes, np.zeros(4))
    np.testing.assert_array_equal(columns["truncated"], 1.0)
    # a car around the camera plane (most of it behind) is almost wholly outside the image
    straddling = camera.kitti_label_columns(cars([[1.0, 0.0]]), np.zeros(1))
    assert straddling["truncated"][0] > 0.95


def test_car_half_out_of_the_left_edge_is_half_truncated():
    # slide a car sideways at 20 m until its unclipped 2D box is centred on the left image edge
    lateral = np.linspace(10.0, 25.0, 3001)
    boxes = cars(np.c_[np.full_like(lateral, 20.0), lateral], yaw=np.pi / 2)
    full, clipped = camera.image_boxes_2d(boxes)
    k = int(np.argmin(np.abs(full[:, 0] + full[:, 2])))
    assert full[k, 1] > 0 and full[k, 3] < camera.IMAGE_SIZE[1] - 1  # only the side is cut
    assert camera.truncation(full[k : k + 1], clipped[k : k + 1])[0] == pytest.approx(0.5, abs=0.01)
    truncated = camera.truncation(full, clipped)
    assert truncated[0] == 0.0 and truncated[-1] == 1.0
    assert (np.diff(truncated) >= -1e-12).all()  # more of it leaves the image as it slides out


def _brute_force_boxes(boxes: np.ndarray, calib) -> np.ndarray:
    """Pinhole projection of the 8 corners, one corner at a time: `(N, 4)` clipped 2D boxes."""
    velo_to_cam = np.eye(4)
    velo_to_cam[:3] = calib.Tr_velo_to_cam
    rectify = np.eye(4)
    rectify[:3, :3] = calib.R0_rect
    result = []
    for x, y, z, l, w, h, yaw in boxes:  # noqa: E741
        us, vs = [], []
        for dx in (-l / 2, l / 2):
            for dy in (-w / 2, w / 2):
                for dz in (-h / 2, h / 2):
                    corner = np.array(
                        [
                            x + np.cos(yaw) * dx - np.sin(yaw) * dy,
                            y + np.sin(yaw) * dx + np.cos(yaw) * dy,
                            z + dz,
                            1.0,
                        ]
                    )
                    u, v, depth = calib.P2 @ (rectify @ velo_to_cam @ corner)
                    us.append(u / depth)
                    vs.append(v / depth)
        result.append(
            [
                min(max(min(us), 0), 1241),
                min(max(min(vs), 0), 374),
                min(max(max(us), 0), 1241),
                min(max(max(vs), 0), 374),
            ]
        )
    return np.array(result)


def test_projection_agrees_with_brute_force_pinhole():
    rng = np.random.default_rng(3)
    count = 60
    boxes = np.c_[
        rng.uniform(5.0, 60.0, count),
        rng.uniform(-20.0, 20.0, count),
        rng.uniform(-1.2, -0.6, count),
        rng.uniform(3.0, 5.0, count),
        rng.uniform(1.5, 2.0, count),
        rng.uniform(1.3, 1.9, count),
        rng.uniform(-np.pi, np.pi, count),
    ]
    real = read_calib(CALIB_FIXTURE)
    expected = _brute_force_boxes(boxes, real)
    _, clipped = camera.image_boxes_2d(boxes, real)
    np.testing.assert_allclose(clipped, expected, atol=1e-6)
    np.testing.assert_allclose(height_px(boxes), expected[:, 3] - expected[:, 1], atol=1e-3)


def test_occlusion_levels_follow_the_thresholds():
    below = np.nextafter(camera.PARTLY_OCCLUDED_FROM, 0.0)
    fraction = [0.0, below, camera.PARTLY_OCCLUDED_FROM, 0.3, camera.LARGELY_OCCLUDED_FROM, 1.0]
    levels = camera.occlusion_level(np.array(fraction))
    np.testing.assert_array_equal(levels, [0, 0, 1, 1, 2, 2])
    assert levels.dtype == np.int32


def test_kitti_protocol_on_camera_labels_ignores_far_cars_in_moderate():
    frames = 50
    near = cars([[15.0, -2.0]])  # detected
    far = cars([[75.0, 3.0]])  # < 25 px: ignored by every KITTI level, missed
    hidden = cars([[25.0, 4.0]])  # largely occluded (level 2): only "hard" counts it, missed
    per_frame = np.concatenate([near, far, hidden])
    occlusion = np.array([0.0, 0.0, 0.7])
    frame_ids = np.repeat([f"{k:06d}" for k in range(frames)], 3)
    gt = BoxTable.from_arrays(
        frame_ids,
        np.tile(per_frame, (frames, 1)),
        label="Car",
        **{
            name: np.tile(values, frames)
            for name, values in camera.kitti_label_columns(per_frame, occlusion).items()
        },
    )
    pred = BoxTable.from_arrays(
        [f"{k:06d}" for k in range(frames)],
        np.tile(near, (frames, 1)),
        score=np.linspace(0.5, 0.9, frames).astype(np.float32),
        label="Car",
    )
    assert evaluate(pred, gt)["Car"]["protocol"] == "kitti"  # auto picks it from the columns
    kitti = evaluate(pred, gt, protocol="kitti")["Car"]
    assert kitti["bev"]["easy"] == pytest.approx(100.0)
    assert kitti["bev"]["moderate"] == pytest.approx(100.0)
    assert kitti["counts"]["moderate"]["gt"] == frames
    assert kitti["counts"]["moderate"]["gt_ignored"] == 2 * frames
    assert kitti["counts"]["hard"]["gt"] == 2 * frames
    assert kitti["bev"]["hard"] < 60.0
    ranged = evaluate(pred, gt, protocol="range")["Car"]
    assert ranged["bev"]["all"] < 40.0
