"""dali compare-domains: the realism statistics on constructed frames, and the command."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.reporting import domains
from dali_cli.store.artifacts import BoxTable, write_boxes, write_frameset


def _points_in_box(box, count: int, intensity: float, rng) -> np.ndarray:
    """`count` points strictly inside the (yaw 0) box `(7,)`, all with `intensity`."""
    local = rng.uniform(-0.45, 0.45, (count, 3)) * box[3:6]
    return np.c_[local + box[:3], np.full(count, intensity)].astype(np.float32)


def _frame(rng):
    """Points and boxes of one frame with known statistics (view +-40 deg):
    in view: 200 ground points (z -1.7, range 5-9 m, intensity 0.2), a car at 15 m with 30
    points and one at 50 m with 4 (intensity 0.6), a car at 25 m without points; out of view:
    a car behind with 40 points and 100 points to the side (intensity 0.9)."""
    ground_range = rng.uniform(5.0, 9.0, 200)
    ground_azimuth = rng.uniform(-0.5, 0.5, 200)
    ground = np.c_[
        ground_range * np.cos(ground_azimuth), ground_range * np.sin(ground_azimuth),
        np.full(200, -1.7), np.full(200, 0.2),
    ]  # fmt: skip
    cars = np.array(
        [
            [15.0, 0.0, -1.0, 4.0, 1.8, 1.5, 0.0],
            [50.0, 3.0, -1.0, 4.0, 1.8, 1.5, 0.0],
            [25.0, -4.0, -1.0, 4.0, 1.8, 1.5, 0.0],
            [-12.0, 0.0, -1.0, 4.0, 1.8, 1.5, 0.0],
        ]
    )
    side = np.c_[rng.uniform(-5, 5, 100), rng.uniform(6, 9, 100), np.zeros(100), np.full(100, 0.9)]
    points = np.concatenate(
        [
            ground,
            _points_in_box(cars[0], 30, 0.6, rng),
            _points_in_box(cars[1], 4, 0.6, rng),
            _points_in_box(cars[3], 40, 0.6, rng),
            side,
        ]
    ).astype(np.float32)
    return points, cars


def test_statistics_of_a_constructed_frame():
    rng = np.random.default_rng(0)
    points, cars = _frame(rng)
    stats = domains.summarize([domains.frame_stats(points, cars, 80.0, rng)] * 2).values
    assert stats["frames"] == 2
    assert stats["points_per_frame"] == 234  # 200 ground + 30 + 4 car points in view
    assert stats["intensity_mean"] == pytest.approx((200 * 0.2 + 34 * 0.6) / 234, rel=1e-6)
    assert stats["intensity_median"] == pytest.approx(0.2)
    assert stats["intensity_p90"] == pytest.approx(0.6)
    assert stats["height_median_m"] == pytest.approx(-1.7)
    assert 5.0 <= stats["range_median_m"] <= 9.0
    # the empty car and the car behind do not count; the far car is beyond 40 m
    assert stats["cars"] == 4 and stats["cars_per_frame"] == 2.0
    assert stats["cars_beyond_40m"] == 2
    assert stats["points_per_car_10_20m"] == 30 and stats["cars_10_20m"] == 2
    assert stats["points_per_car_40_60m"] == 4
    assert stats["points_per_car_20_30m"] is None and stats["cars_20_30m"] == 0
    # the full circle counts the car behind and the side points too
    full = domains.summarize([domains.frame_stats(points, cars, None, rng)]).values
    assert full["points_per_frame"] == len(points) and full["cars"] == 3


def test_frames_weigh_by_their_point_counts_not_their_samples():
    rng = np.random.default_rng(1)
    big = np.c_[np.full(10_000, 10.0), rng.uniform(-1, 1, 10_000), np.zeros(10_000),
                np.full(10_000, 0.1)].astype(np.float32)  # fmt: skip
    small = np.c_[np.full(1000, 10.0), rng.uniform(-1, 1, 1000), np.zeros(1000),
                  np.full(1000, 0.5)].astype(np.float32)  # fmt: skip
    frames = [domains.frame_stats(p, np.zeros((0, 7)), 80.0, rng) for p in (big, small)]
    assert len(frames[0].intensity) == domains.SAMPLE_PER_FRAME  # sampled
    stats = domains.summarize(frames).values
    assert stats["points_per_frame"] == 5500
    assert stats["intensity_mean"] == pytest.approx((10_000 * 0.1 + 1000 * 0.5) / 11_000)
    assert stats["intensity_median"] == pytest.approx(0.1)
    assert stats["cars_per_frame"] == 0 and stats["points_per_car_10_20m"] is None


def test_view_is_an_angle_around_forward():
    xy = np.array([[10.0, 0.0], [10.0, 8.0], [10.0, 9.0], [-10.0, 0.0], [0.0, 10.0]])
    # atan(8/10) = 38.7 deg, atan(9/10) = 42 deg
    np.testing.assert_array_equal(domains.in_view(xy, 80.0), [True, True, False, False, False])
    assert domains.in_view(xy, 360.0).all() and domains.in_view(xy, None).all()


def _write_domain(directory, points_by_frame, cars_by_frame):
    write_frameset(directory, [(f"{k:06d}", p) for k, p in enumerate(points_by_frame)], "kitti")
    ids = [f"{k:06d}" for k, cars in enumerate(cars_by_frame) for _ in cars]
    boxes = np.concatenate(cars_by_frame)
    labels = np.array(["Car", "Car", "Van", "Car"] * len(cars_by_frame), dtype=object)
    write_boxes(directory, BoxTable.from_arrays(ids, boxes, label=labels))


def test_command_prints_the_table_and_writes_json_and_plots(tmp_path):
    pytest.importorskip("matplotlib")
    rng = np.random.default_rng(2)
    one, cars = _frame(rng)
    bright = one.copy()
    bright[:, 3] = 0.8
    _write_domain(tmp_path / "real", [one, one], [cars, cars])
    _write_domain(tmp_path / "synth", [bright], [cars])
    runner = CliRunner()
    out = tmp_path / "report"
    args = ["compare-domains", f"real={tmp_path / 'real'}", str(tmp_path / "synth"),
            "--out", str(out)]  # fmt: skip
    result = runner.invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "real" in result.output and "synth" in result.output
    assert "0.80 / 0.80 / 0.80" in result.output  # the bright set's intensity row
    document = json.loads((out / "domains.json").read_text())
    real, synth = document["domains"]["real"], document["domains"]["synth"]
    assert real["frames"] == 2 and synth["frames"] == 1
    # the third box is a Van: not a car; the 25 m car has no points
    assert real["cars_per_frame"] == 2.0 and real["points_per_car_20_30m"] is None
    assert synth["intensity_median"] == pytest.approx(0.8)
    assert document["settings"]["view_deg"] == 80.0
    for name in ("intensity", "height", "range", "car_range", "points_per_car"):
        assert (out / f"{name}.png").stat().st_size > 1000
    assert (out / "manifest.json").is_file()
    again = runner.invoke(main, args)
    assert again.exit_code == 0 and "up to date" in again.output


def test_command_refuses_bad_inputs_and_foreign_outputs(tmp_path):
    runner = CliRunner()
    rng = np.random.default_rng(3)
    one, cars = _frame(rng)
    _write_domain(tmp_path / "a", [one], [cars])
    result = runner.invoke(main, ["compare-domains", str(tmp_path / "missing")])
    assert result.exit_code == 2 and "missing" in result.output
    (tmp_path / "empty").mkdir()
    result = runner.invoke(main, ["compare-domains", str(tmp_path / "empty")])
    assert result.exit_code == 1 and "frames.zarr" in result.output
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    result = runner.invoke(main, ["compare-domains", str(tmp_path / "a"), "--out", str(mine)])
    assert result.exit_code == 1 and "exists" in result.output
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
    result = runner.invoke(main, ["compare-domains", f"x={tmp_path / 'a'}", f"x={tmp_path / 'a'}"])
    assert result.exit_code == 2 and "differ" in result.output
