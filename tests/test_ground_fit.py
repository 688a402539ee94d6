"""`pseudo-label --fit-ground` (dali_cli.labels.ground_fit): each box's bottom on the ground around it."""

from __future__ import annotations

import numpy as np
import pytest

from dali_cli.labels.ground_fit import GroundFit, fit_heights, ground_under


def road(slope_x: float, slope_y: float, offset: float, rng, count=6000, noise=0.02):
    """Points `(count, 4)` on the plane z = offset + slope_x x + slope_y y over 0..60 x -20..20 m,
    with range noise: a sloped road."""
    xy = rng.uniform([0.0, -20.0], [60.0, 20.0], size=(count, 2))
    z = offset + slope_x * xy[:, 0] + slope_y * xy[:, 1] + rng.normal(0, noise, count)
    return np.column_stack([xy, z, np.full(count, 0.2)])


def car_points(box: np.ndarray, rng, count=300) -> np.ndarray:
    """Points `(count, 4)` on the box's faces above its bottom + 0.2 m (a car's body)."""
    x, y, z, length, width, height, yaw = box
    u = rng.uniform(-length / 2, length / 2, count)
    v = rng.choice([-width / 2, width / 2], count)
    w = rng.uniform(-height / 2 + 0.2, height / 2, count)
    c, s = np.cos(yaw), np.sin(yaw)
    return np.column_stack([x + c * u - s * v, y + s * u + c * v, z + w, np.full(count, 0.5)])


def scene(rng, slope=(0.02, -0.01), offset=-1.73):
    """A sloped road, three cars standing on it, a wall beside the first and clutter above the
    road: points `(n, 4)` and the true boxes `(3, 7)`."""
    truth = []
    for x, y, yaw in ((12.0, 4.0, 0.3), (30.0, -6.0, 1.2), (50.0, 2.0, -0.4)):
        ground = offset + slope[0] * x + slope[1] * y
        truth.append([x, y, ground + 0.75, 4.0, 1.7, 1.5, yaw])
    truth = np.array(truth)
    wall = np.column_stack(
        [
            rng.uniform(8, 16, 800),
            np.full(800, 9.0),
            rng.uniform(-1.7, 2.0, 800),
            np.full(800, 0.4),
        ]
    )
    clutter = np.column_stack(
        [
            rng.uniform(0, 60, 300),
            rng.uniform(-20, 20, 300),
            rng.uniform(0.5, 3.0, 300),
            np.ones(300),
        ]
    )
    parts = [road(*slope, offset, rng), wall, clutter, *[car_points(b, rng) for b in truth]]
    return np.concatenate(parts).astype(np.float32), truth


@pytest.mark.parametrize("slope", [(0.0, 0.0), (0.02, -0.01), (-0.03, 0.02)])
def test_boxes_off_the_ground_come_back_onto_it(slope):
    rng = np.random.default_rng(0)
    points, truth = scene(rng, slope)
    pseudo = truth.copy()
    pseudo[:, 2] += [0.25, -0.2, 0.12]  # floating, sunk, floating
    fitted, moved = fit_heights(pseudo, points, GroundFit())
    assert moved.all()
    np.testing.assert_allclose(fitted[:, 2], truth[:, 2], atol=0.02)
    np.testing.assert_array_equal(np.delete(fitted, 2, axis=1), np.delete(pseudo, 2, axis=1))


def test_the_car_and_its_neighbours_are_not_taken_for_ground():
    """Points of the box's own car and of a car parked right beside it lie above the road: the
    height stays the road's, not the cars' bodies'."""
    rng = np.random.default_rng(1)
    points, truth = scene(rng)
    beside = truth[0].copy()
    beside[1] += 2.0  # a second car 2 m to the side
    points = np.concatenate([points, car_points(beside, rng, 2000).astype(np.float32)])
    boxes = np.array([truth[0], beside])
    heights = ground_under(boxes, points, GroundFit())
    road_height = -1.73 + 0.02 * boxes[:, 0] - 0.01 * boxes[:, 1]  # scene()'s default road
    np.testing.assert_allclose(heights, road_height, atol=0.01)


def test_boxes_without_ground_or_far_from_it_keep_their_height():
    rng = np.random.default_rng(2)
    points, truth = scene(rng)
    lonely = np.array([[200.0, 0.0, -1.0, 4.0, 1.7, 1.5, 0.0]])  # no point within 10 m
    fitted, moved = fit_heights(lonely, points, GroundFit())
    assert not moved.any() and np.array_equal(fitted, lonely)
    high = truth[:1].copy()
    high[0, 2] += 0.6  # the road lies 0.6 m below: beyond max_shift_m (0.4), and the window
    fitted, moved = fit_heights(high, points, GroundFit(max_shift_m=0.4, window_m=1.0))
    assert not moved.any() and np.array_equal(fitted, high)
    fitted, moved = fit_heights(high, points, GroundFit(max_shift_m=0.7, window_m=1.0))
    assert moved.all() and abs(fitted[0, 2] - truth[0, 2]) < 0.02
    assert fit_heights(np.zeros((0, 7)), points, GroundFit())[0].shape == (0, 7)


def test_settings_are_checked():
    with pytest.raises(ValueError, match="ring_m"):
        GroundFit(ring_m=0)
    with pytest.raises(ValueError, match="min_points"):
        GroundFit(min_points=2)


class FloatingDetector:
    """Finds every car of test_box_fit's stage scenes 0.25 m above where it stands."""

    def predict(self, points_list, scale=1.0, mount_height_m=None):
        from test_box_fit import stage_cars

        results = []
        for points in points_list:
            boxes = stage_cars(int(round(float(points[0, 3]) * 100))).copy()
            boxes[:, 2] += 0.25
            results.append((boxes, np.full(len(boxes), 0.9, np.float32)))
        return results


def test_the_stage_puts_the_boxes_on_the_ground_and_records_it(tmp_path, monkeypatch):
    import json

    from stub_stage import pseudo_label_cli, write_stub_inputs
    from test_box_fit import stage_cars, stage_points

    import stages.pseudo_label
    from dali_cli.store.artifacts import read_boxes

    target, model = write_stub_inputs(tmp_path, [stage_points(i) for i in range(3)])
    monkeypatch.setattr(stages.pseudo_label, "load_detector", lambda _: FloatingDetector())

    for name, options in (("plain", []), ("ground", ["--fit-ground"])):
        result = pseudo_label_cli(model, target, tmp_path / name, *options)
        assert result.exit_code == 0, result.output
    for name, lift in (("plain", 0.25), ("ground", 0.0)):
        table = read_boxes(tmp_path / name)
        for frame_id, rows in table.rows_by_frame().items():
            truth_z = stage_cars(int(frame_id))[:, 2]
            np.testing.assert_allclose(np.sort(table.boxes[rows, 2]), np.sort(truth_z + lift),
                                       atol=0.01)  # fmt: skip
    manifest = json.loads((tmp_path / "ground" / "manifest.json").read_text())
    assert manifest["params"]["fit_ground"] == GroundFit().record()
    assert (
        "fit_ground" not in json.loads((tmp_path / "plain" / "manifest.json").read_text())["params"]
    )  # earlier labels stay up to date
    summary = json.loads((tmp_path / "ground" / "summary.json").read_text())["ground_fit"]
    assert summary["boxes_moved"] == 6 and summary["boxes_kept"] == 0
    assert summary["mean_shift_m"] == pytest.approx(-0.25, abs=0.01)
    assert "ground fit: 6 boxes" in result.output
