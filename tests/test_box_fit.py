"""The point fit of pseudo boxes (dali_cli.labels.box_fit, `dali pseudo-label --fit-points`): a box
placed off a car seen on its near faces is moved back onto them, a box already on them stays,
the fit follows the scene under rigid motion, ignores the ground, other cars' points and boxes
with too few points; the stage records it and recounts the points."""

from __future__ import annotations

import json

import numpy as np
import pytest
from stub_stage import pseudo_label_cli, write_stub_inputs

from dali_cli.geometry import count_points_in_boxes, wrap_angle
from dali_cli.labels.box_fit import PointFit, fit_boxes
from dali_cli.labels.pose_search import pose_costs
from dali_cli.store.artifacts import read_boxes

MOUNT = 1.73
LWH = np.array([3.9, 1.6, 1.5])


def car(x: float, y: float, yaw: float) -> np.ndarray:
    return np.array([x, y, -MOUNT + LWH[2] / 2, *LWH, yaw])


def near_faces(box: np.ndarray, per_face: int = 150, seed: int = 0) -> np.ndarray:
    """Points `(n, 4)` float32 on the faces of `box` that face a sensor at the origin (as a
    LiDAR sees a car: on its sides, not inside it), from 0.25 m above the bottom to the top."""
    rng = np.random.default_rng(seed)
    c, s = np.cos(box[6]), np.sin(box[6])
    half_l, half_w = box[3] / 2, box[4] / 2
    clouds = []
    for axis, half, other in ((0, half_l, half_w), (1, half_w, half_l)):
        for sign in (-1.0, 1.0):
            normal = np.zeros(2)
            normal[axis] = sign
            world_normal = np.array([c * normal[0] - s * normal[1], s * normal[0] + c * normal[1]])
            face_centre = box[:2] + half * world_normal
            if world_normal @ face_centre >= 0:  # facing away from the sensor
                continue
            local = np.zeros((per_face, 2))
            local[:, axis] = sign * half
            local[:, 1 - axis] = rng.uniform(-other, other, per_face)
            xy = local @ np.array([[c, s], [-s, c]]) + box[:2]
            bottom = box[2] - box[5] / 2
            z = rng.uniform(bottom + 0.25, bottom + box[5], per_face)
            clouds.append(np.c_[xy, z])
    xyz = np.concatenate(clouds)
    return np.c_[xyz, np.full(len(xyz), 0.3)].astype(np.float32)


def ground(seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform([0, -20], [40, 20], (3000, 2))
    return np.c_[xy, np.full(len(xy), -MOUNT), np.full(len(xy), 0.1)].astype(np.float32)


def moved(box: np.ndarray, along: float, across: float, turn_deg: float) -> np.ndarray:
    c, s = np.cos(box[6]), np.sin(box[6])
    out = box.copy()
    out[0] += c * along - s * across
    out[1] += s * along + c * across
    out[6] = wrap_angle(box[6] + np.radians(turn_deg))
    return out


def pose_error(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(BEV centre distance m, heading difference deg) of two boxes."""
    return float(np.hypot(*(a[:2] - b[:2]))), float(np.degrees(abs(wrap_angle(a[6] - b[6]))))


@pytest.mark.parametrize(
    "truth, offset",
    [
        (car(12.0, 4.0, 0.3), (0.4, -0.1, 3.0)),
        (car(20.0, -6.0, -1.2), (-0.7, 0.15, -6.0)),
        (car(9.0, 1.0, 2.6), (0.35, 0.0, 5.0)),
    ],
)
def test_a_box_off_the_car_is_moved_back_onto_its_faces(truth, offset):
    start = moved(truth, *offset)
    points = np.r_[near_faces(truth), ground()]
    (fitted,), (used,) = fit_boxes(start[None], points)
    distance, turn = pose_error(fitted, truth)
    assert distance < 0.08 and turn < 1.5, (distance, turn)
    assert pose_error(start, truth)[0] > 0.3  # the start was well off
    np.testing.assert_array_equal(fitted[2:6], start[2:6])  # z and size kept
    assert used >= PointFit().min_points


def test_a_box_on_its_faces_stays_where_it_is():
    truth = car(15.0, 3.0, 0.7)
    (fitted,), _ = fit_boxes(truth[None], np.r_[near_faces(truth), ground()])
    np.testing.assert_allclose(fitted, truth, atol=1e-12)


@pytest.mark.parametrize("angle, shift", [(0.9, (5.0, -2.0)), (-2.2, (-3.0, 7.0))])
def test_the_fit_follows_the_scene_under_rigid_motion(angle, shift):
    truth = car(14.0, 5.0, -0.4)
    start = moved(truth, 0.5, -0.1, 4.0)
    points = near_faces(truth)
    c, s = np.cos(angle), np.sin(angle)

    def motion(xy):
        return xy @ np.array([[c, s], [-s, c]]) + shift

    (fitted,), _ = fit_boxes(start[None], points)
    moved_points = points.copy()
    moved_points[:, :2] = motion(points[:, :2].astype(np.float64))
    moved_start = start.copy()
    moved_start[:2], moved_start[6] = motion(start[:2]), wrap_angle(start[6] + angle)
    (fitted_moved,), _ = fit_boxes(moved_start[None], moved_points)
    np.testing.assert_allclose(fitted_moved[:2], motion(fitted[:2]), atol=1e-3)
    assert abs(wrap_angle(fitted_moved[6] - fitted[6] - angle)) < 1e-6


def test_ground_and_another_cars_points_do_not_pull_the_box():
    truth, other = car(12.0, 3.0, 0.0), car(16.6, 3.0, 0.0)  # 0.7 m behind it, same lane
    start = moved(truth, 0.5, 0.0, 0.0)
    alone, _ = fit_boxes(start[None], near_faces(truth))
    with_scene, _ = fit_boxes(
        np.stack([start, other]), np.r_[near_faces(truth), near_faces(other, seed=3), ground()]
    )
    np.testing.assert_allclose(with_scene[0], alone[0], atol=1e-9)
    assert pose_error(with_scene[0], truth)[0] < 0.08


def test_a_box_with_too_few_points_is_kept():
    truth = car(30.0, -5.0, 1.0)
    start = moved(truth, 0.5, 0.1, 3.0)
    points = near_faces(truth, per_face=4)  # 4-8 points: under min_points
    (fitted,), (used,) = fit_boxes(start[None], points)
    assert used < PointFit().min_points
    np.testing.assert_array_equal(fitted, start)
    fitted, used = fit_boxes(np.zeros((0, 7)), points)
    assert fitted.shape == (0, 7) and used.shape == (0,)


def plain_costs(uv: np.ndarray, half_lw: np.ndarray, grid: np.ndarray, fit: PointFit):
    """The module docstring's cost, pose by pose, in float64: each point moved into the shifted,
    turned box's frame and scored (the reference of the vectorized pose_costs)."""
    costs = []
    for du, dv, turn in grid:
        u, v = uv[:, 0] - du, uv[:, 1] - dv
        a = np.cos(turn) * u + np.sin(turn) * v
        b = -np.sin(turn) * u + np.cos(turn) * v
        outside = np.maximum(np.abs(a) - half_lw[0], 0) + np.maximum(np.abs(b) - half_lw[1], 0)
        side = np.clip(np.minimum(half_lw[0] - np.abs(a), half_lw[1] - np.abs(b)), 0,
                       fit.side_cap_m)  # fmt: skip
        costs.append((side**2).sum() + fit.outside_weight * (outside**2).sum())
    return np.array(costs)


@pytest.mark.parametrize("chunk", [1, 7, 64, 10**4])
def test_pose_costs_equal_the_plain_cost_of_every_pose(chunk):
    fit = PointFit(along_m=0.3, across_m=0.1, turn_deg=4.0)  # a smaller grid, the same cost
    truth = car(18.0, 3.0, 0.4)
    points = np.concatenate([near_faces(truth, per_face=60), near_faces(moved(truth, 1, 0, 0))])
    c, s = np.cos(truth[6]), np.sin(truth[6])
    rel = points[:, :2].astype(np.float64) - truth[:2]
    uv = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]], 1)
    grid = fit.grid()
    expected = plain_costs(uv, LWH[:2] / 2, grid, fit)
    got = pose_costs(uv, LWH[:2] / 2, fit, chunk=chunk)
    assert got.shape == (len(grid),) and got.dtype == np.float64
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-4)  # float32 elementwise
    assert np.argmin(got) == np.argmin(expected)


def test_grid_holds_the_unmoved_pose_and_bad_parameters_are_refused():
    fit = PointFit(along_m=0.1, along_step_m=0.05, across_m=0.05, across_step_m=0.05,
                   turn_deg=2, turn_step_deg=1)  # fmt: skip
    along, across, turn = (np.array([-0.1, -0.05, 0, 0.05, 0.1]), np.array([-0.05, 0, 0.05]),
                           np.radians([-2, -1, 0, 1, 2]))  # fmt: skip
    order = np.stack(np.meshgrid(along, across, turn, indexing="ij"), -1).reshape(-1, 3)
    np.testing.assert_allclose(fit.grid(), order, atol=1e-12)  # turn fastest, then across
    grid = PointFit().grid()
    assert (np.abs(grid).sum(1) == 0).sum() == 1
    assert np.isclose(grid[:, 0].max(), PointFit().along_m)
    assert np.isclose(np.degrees(grid[:, 2].max()), PointFit().turn_deg)
    for bad in ({"along_m": -1}, {"turn_step_deg": 0}, {"min_points": 0}, {"max_points": 5}):
        with pytest.raises(ValueError):
            PointFit(**bad)


# ---------------------------------------------------------------------------------------------
# the stage


def stage_cars(frame: int) -> np.ndarray:
    return np.stack([car(10.0 + frame, 4.0, 0.2 * frame), car(22.0, -5.0, -0.6 + 0.1 * frame)])


class AlongOffsetDetector:
    """Finds every car 0.45 m ahead of where it is (a typical pseudo-box error along the car)."""

    def predict(self, points_list, scale=1.0, mount_height_m=None):
        results = []
        for points in points_list:
            frame = int(round(float(points[0, 3]) * 100))
            boxes = np.stack([moved(box, 0.45, 0.0, 0.0) for box in stage_cars(frame)])
            results.append((boxes, np.full(len(boxes), 0.9, np.float32)))
        return results


def stage_points(frame: int) -> np.ndarray:
    points = np.concatenate([near_faces(box, seed=frame) for box in stage_cars(frame)])
    points[0, 3] = frame / 100.0
    return np.r_[points, ground(frame)]


def test_the_stage_fits_the_boxes_by_default_recounts_and_records_the_fit(tmp_path, monkeypatch):
    target, model = write_stub_inputs(tmp_path, [stage_points(i) for i in range(3)])
    import stages.pseudo_label

    monkeypatch.setattr(stages.pseudo_label, "load_detector", lambda _: AlongOffsetDetector())

    def label(out, *options):
        return pseudo_label_cli(model, target, out, *options)

    for out, options in ((tmp_path / "plain", ["--no-fit-points"]), (tmp_path / "fit", [])):
        result = label(out, *options)
        assert result.exit_code == 0, result.output
    errors = {}
    for name in ("plain", "fit"):
        table = read_boxes(tmp_path / name)
        worst = 0.0
        for frame_id, rows in table.rows_by_frame().items():
            truth = stage_cars(int(frame_id))
            for box in table.boxes[rows]:
                worst = max(worst, min(pose_error(box, t)[0] for t in truth))
        errors[name] = worst
        points = {f"{i:03d}": stage_points(i) for i in range(3)}
        for frame_id, rows in table.rows_by_frame().items():
            counts = count_points_in_boxes(points[frame_id], table.boxes[rows])
            np.testing.assert_array_equal(table["num_points"][rows], counts)
    assert errors["plain"] == pytest.approx(0.45, abs=1e-6) and errors["fit"] < 0.08
    fit_manifest = json.loads((tmp_path / "fit" / "manifest.json").read_text())
    assert fit_manifest["params"]["fit_points"] == PointFit().record()
    plain_manifest = json.loads((tmp_path / "plain" / "manifest.json").read_text())
    assert "fit_points" not in plain_manifest["params"]  # earlier labels stay up to date
    summary = json.loads((tmp_path / "fit" / "summary.json").read_text())
    assert summary["point_fit"]["boxes_fitted"] == 6
    assert summary["point_fit"]["mean_shift_m"] == pytest.approx(0.45, abs=0.08)
    same = label(tmp_path / "fit", "--fit-points")  # the default, named: the same artifact
    assert same.exit_code == 0 and "up to date" in same.output
    again = label(tmp_path / "fit", "--no-fit-points")  # a different artifact: rebuilt
    assert again.exit_code == 0 and "up to date" not in again.output
    assert "point_fit" not in json.loads((tmp_path / "fit" / "summary.json").read_text())
