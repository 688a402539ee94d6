"""dali synth: tight labels, ground height, occlusion, windows, determinism, domain gap, errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from click.testing import CliRunner

from dali_cli import geometry, synth
from dali_cli.cli import main
from dali_cli.importers.camera import kitti_label_columns
from dali_cli.raycast import cast_into_box
from dali_cli.sensors import get_profile
from dali_cli.store.artifacts import FrameSet, read_boxes
from dali_cli.world import cars as world_cars
from dali_cli.world import scan as world_scan
from dali_cli.world import scene as world_scene


def _excess(frame: synth.SynthFrame) -> np.ndarray:
    """How far each car point lies outside its label box (<= 0 inside), `(m,)` metres."""
    car = frame.owner >= 0
    boxes = frame.boxes[frame.owner[car]]
    return np.max(
        np.abs(geometry.points_in_box_frames(frame.points[car].astype(np.float64), boxes))
        - boxes[:, 3:6] / 2,
        axis=1,
    )


def test_car_points_lie_in_their_label_boxes():
    kitti = get_profile("kitti")
    exact = dataclasses.replace(kitti, range_noise_sigma_m=0.0, ray_dropout=0.0)
    frame = synth.synth_frame(6, 0, exact, kitti)
    assert len(frame.boxes) >= 3
    assert _excess(frame).max() <= 1e-4
    # ... with room to spare, as annotators draw them: the body fills the box less its slack
    car = frame.owner >= 0
    boxes = frame.boxes[frame.owner[car]]
    local = geometry.points_in_box_frames(frame.points[car].astype(np.float64), boxes)
    room = boxes[:, 3:6] / 2 - np.abs(local)  # (m, 3) to each face, >= 0 inside
    room[:, 2] = boxes[:, 5] / 2 - local[:, 2]  # the top (the wheels stand on the box bottom)
    assert (room >= world_cars.LABEL_SLACK_M - 1e-4).all()
    assert (room.min(axis=0) <= world_cars.LABEL_SLACK_M + 0.03).all()  # and the body fills it
    np.testing.assert_array_equal(frame.num_points, np.bincount(frame.owner[frame.owner >= 0]))
    noisy = synth.synth_frame(6, 0, kitti, kitti)
    assert _excess(noisy).max() <= 5 * kitti.range_noise_sigma_m + 1e-4
    # labels: every car has points, centers 3-80 m away, yaw normalized, no two footprints overlap
    for f in (frame, noisy):
        assert (f.num_points >= 1).all()
        distance = np.hypot(f.boxes[:, 0], f.boxes[:, 1])
        assert ((distance >= 3.0) & (distance <= 80.0)).all()
        assert ((f.boxes[:, 6] >= -np.pi) & (f.boxes[:, 6] < np.pi)).all()
        corners = geometry.bev_corners(f.boxes)
        for k in range(len(corners)):
            others = np.delete(corners, k, axis=0)
            assert not geometry.footprints_overlap(corners[k], others).any()
        assert np.isfinite(f.points).all() and f.points.dtype == np.float32
        assert (f.points[:, 3] >= 0).all() and (f.points[:, 3] <= 1).all()
        assert ((f.occlusion >= 0) & (f.occlusion <= 1)).all()


@pytest.mark.parametrize("name", ["kitti", "nuscenes"])
def test_ground_is_at_minus_mount_height_under_the_sensor(name):
    profile = get_profile(name)
    frame = synth.synth_frame(2, 1, profile, profile)
    ground = frame.points[frame.owner == -1]
    near = np.hypot(ground[:, 0], ground[:, 1]) < 10.0
    assert near.sum() > 100
    assert abs(np.median(ground[near, 2]) + profile.mount_height_m) < 0.03
    scene = world_scene.generate_scene(synth.frame_rng(2, 1), profile, profile)
    assert scene.ground.height(np.zeros(2)) == pytest.approx(-profile.mount_height_m, abs=1e-12)
    # cars stand on the ground: box bottom = ground height at the box center
    bottoms = scene.cars[:, 2] - scene.cars[:, 5] / 2
    np.testing.assert_allclose(bottoms, scene.ground.height(scene.cars[:, :2]), atol=1e-9)


def _scene_with_cars(boxes: np.ndarray, mount: float = 1.73) -> world_scene.SynthScene:
    ground = world_scene.Ground(mount, np.zeros(2), np.zeros((1, 2)), np.zeros(1), np.zeros(1))
    far_wall = world_scene._box_mesh(np.array([0.0, 300.0, 0.0, 1.0, 1.0, 1.0, 0.0]))
    return world_scene.SynthScene(
        ground=ground,
        cars=np.asarray(boxes, np.float64),
        car_models=np.arange(len(boxes)),
        car_reflectance=np.ones(len(boxes)),
        clutter_vertices=far_wall[0],
        clutter_faces=far_wall[1],
        face_reflectance=np.ones(12),
        road_heading=0.0,
        lane_lines=np.zeros(0),
    )


def test_cars_occlude_each_other_and_the_estimate_says_so():
    kitti = dataclasses.replace(get_profile("kitti"), range_noise_sigma_m=0.0, ray_dropout=0.0)
    front = [10.0, 0.0, -1.73 + 0.75, 4.0, 1.8, 1.5, 0.0]
    behind = [20.0, 0.0, -1.73 + 0.75, 4.0, 1.8, 1.5, 0.0]
    alone = world_scan.scan_scene(_scene_with_cars([behind]), kitti, np.random.default_rng(0))
    both = world_scan.scan_scene(_scene_with_cars([front, behind]), kitti, np.random.default_rng(0))
    behind_alone = int((alone.owner == 0).sum())
    behind_hidden = int((both.owner == 1).sum())
    assert behind_alone > 200 and behind_hidden < 0.3 * behind_alone
    occlusion = 1 - both.car_visible_rays / both.car_unoccluded_rays
    assert occlusion[0] == 0.0 and occlusion[1] > 0.7
    # rays do not pass through a car body: no ground or far-car point inside the front car's box
    local = geometry.points_in_box_frames(
        both.points.astype(np.float64), np.array([front] * len(both.points))
    )
    inside = np.all(np.abs(local) <= np.array(front[3:6]) / 2, axis=1)
    assert inside.sum() > 100 and (both.owner[inside] == 0).all()


@pytest.mark.parametrize("field_of_view", [(-180.0, 180.0), (90.0, 270.0), (-60.0, 60.0)])
def test_ray_windows_hold_every_ray_that_can_hit_the_car(field_of_view):
    profile = dataclasses.replace(
        get_profile("nuscenes"), azimuth_min_deg=field_of_view[0], azimuth_max_deg=field_of_view[1]
    )
    pattern = world_scan._pattern(profile)
    rng = np.random.default_rng(3)
    model = world_cars.pool_car(0)
    for _ in range(12):
        distance, azimuth = rng.uniform(3.5, 40), rng.uniform(-np.pi, np.pi)
        box = np.array(
            [
                distance * np.cos(azimuth),
                distance * np.sin(azimuth),
                rng.uniform(-1.5, 1.0),
                rng.uniform(3.5, 5.5),
                rng.uniform(1.6, 2.1),
                rng.uniform(1.3, 1.9),
                rng.uniform(-np.pi, np.pi),
            ]
        )
        window = world_scan.box_ray_window(pattern, box)
        hits = cast_into_box(model.bvh(), np.zeros(3), pattern.directions, box)
        assert np.isin(np.flatnonzero(hits.hit), window).all()
        assert len(window) < 0.2 * len(pattern.directions)


def test_footprint_overlap_matches_polygon_intersection():
    shapely = pytest.importorskip("shapely")
    rng = np.random.default_rng(8)
    boxes = np.c_[rng.uniform(-6, 6, (200, 2)), np.zeros(200), rng.uniform(0.3, 5, (200, 2)),
                  np.ones(200), rng.uniform(-np.pi, np.pi, 200)]  # fmt: skip
    corners = geometry.bev_corners(boxes)
    polygons = [shapely.Polygon(c) for c in corners]
    for k in range(0, 200, 10):
        expected = np.array([polygons[k].intersection(p).area > 1e-9 for p in polygons])
        np.testing.assert_array_equal(geometry.footprints_overlap(corners[k], corners), expected)


def test_frames_are_deterministic_per_seed_and_index():
    nuscenes = get_profile("nuscenes")
    first = synth.synth_frame(9, 4, nuscenes, nuscenes)
    other = synth.synth_frame(9, 3, nuscenes, nuscenes)
    again = synth.synth_frame(9, 4, nuscenes, nuscenes)
    np.testing.assert_array_equal(first.points, again.points)
    np.testing.assert_array_equal(first.boxes, again.boxes)
    assert len(other.points) != len(first.points) or not np.array_equal(other.points, first.points)


def synth_nuscenes(frames: str, out, *options: str) -> list[str]:
    """`dali synth` of nuScenes frames with seed 7."""
    return ["synth", "--sensor", "nuscenes", "--frames", frames, "--seed", "7", *options,
            "--out", str(out)]  # fmt: skip


def test_synth_command_output_independent_of_frame_count_and_workers(tmp_path):
    runner = CliRunner()
    one = runner.invoke(main, synth_nuscenes("3", tmp_path / "a", "--workers", "1"))
    assert one.exit_code == 0, one.output
    two = runner.invoke(main, synth_nuscenes("2", tmp_path / "b", "--workers", "2"))
    assert two.exit_code == 0, two.output
    a, b = FrameSet(tmp_path / "a"), FrameSet(tmp_path / "b")
    assert a.frame_ids == ["000000", "000001", "000002"] and b.frame_ids == a.frame_ids[:2]
    for index in range(2):
        np.testing.assert_array_equal(a.frame(index), b.frame(index))
    boxes_a, boxes_b = read_boxes(tmp_path / "a"), read_boxes(tmp_path / "b")
    in_first_two = np.isin(boxes_a.frame_id.astype(str), ["000000", "000001"])
    np.testing.assert_array_equal(boxes_a.boxes[in_first_two], boxes_b.boxes)
    for column in ("num_points", "occlusion", "kind", "car_model"):
        assert column in boxes_a.columns
    # KITTI label fields of the virtual camera, from the boxes and occlusion alone
    expected = kitti_label_columns(boxes_a.boxes, boxes_a["occlusion"])
    for column, values in expected.items():
        np.testing.assert_array_equal(boxes_a[column], values)
        assert boxes_a[column].dtype == values.dtype
    assert a.sensor == "nuscenes" and a.attrs["cars_profile"] == "nuscenes"
    rerun = runner.invoke(main, synth_nuscenes("3", tmp_path / "a"))
    assert rerun.exit_code == 0 and "up to date" in rerun.output


def test_domain_gap_car_sizes_and_sensor_density():
    nuscenes, kitti, waymo = get_profile("nuscenes"), get_profile("kitti"), get_profile("waymo")
    sizes = {}
    for cars in (kitti, waymo):
        scenes = [
            world_scene.generate_scene(synth.frame_rng(1, k), nuscenes, cars) for k in range(12)
        ]
        sizes[cars.name] = np.concatenate([s.cars[:, 3:6] for s in scenes]).mean(axis=0)
    expected_gap = np.subtract(waymo.car_mean_lwh_m, kitti.car_mean_lwh_m)  # 0.77, 0.46, 0.20
    np.testing.assert_allclose(sizes["waymo"] - sizes["kitti"], expected_gap, atol=0.12)
    # the same scenes scanned by a 64-beam and a 32-beam sensor: denser points per car
    per_car_dense, per_car_sparse, distance = [], [], []
    for index in range(4):
        scene = world_scene.generate_scene(synth.frame_rng(1, index), kitti, kitti)
        dense = world_scan.scan_scene(scene, kitti, np.random.default_rng(0))
        sparse = world_scan.scan_scene(
            scene,
            dataclasses.replace(nuscenes, mount_height_m=kitti.mount_height_m),
            np.random.default_rng(0),
        )
        cars = len(scene.cars)
        per_car_dense.append(np.bincount(dense.owner[dense.owner >= 0], minlength=cars))
        per_car_sparse.append(np.bincount(sparse.owner[sparse.owner >= 0], minlength=cars))
        distance.append(np.hypot(scene.cars[:, 0], scene.cars[:, 1]))
    per_car_dense, per_car_sparse = np.concatenate(per_car_dense), np.concatenate(per_car_sparse)
    distance = np.concatenate(distance)
    seen = per_car_sparse > 20
    assert seen.sum() >= 3
    assert np.median(per_car_dense[seen] / per_car_sparse[seen]) > 3.0
    # and points per car fall with range
    visible = per_car_dense > 0
    ranks = (
        np.argsort(np.argsort(distance[visible])),
        np.argsort(np.argsort(per_car_dense[visible])),
    )
    assert np.corrcoef(*ranks)[0, 1] < -0.4


def test_bad_input_gives_clear_errors_and_no_output(tmp_path):
    runner = CliRunner()
    result = runner.invoke(
        main, ["synth", "--sensor", "velodyne9000", "--frames", "1", "--out", str(tmp_path / "x")]
    )
    assert (
        result.exit_code == 1 and "velodyne9000" in result.output and "available" in result.output
    )
    bad = tmp_path / "bad.toml"
    bad.write_text("[mine]\nbeams = 0\n")
    result = runner.invoke(
        main,
        [
            "synth",
            "--sensor",
            "mine",
            "--sensors",
            str(bad),
            "--frames",
            "1",
            "--out",
            str(tmp_path / "x"),
        ],
    )
    assert result.exit_code == 1 and "bad.toml" in result.output
    result = runner.invoke(
        main, ["synth", "--sensor", "kitti", "--frames", "0", "--out", str(tmp_path / "x")]
    )
    assert result.exit_code == 2
    assert not (tmp_path / "x").exists()


def test_returns_weaken_with_range_and_darkness_and_the_ego_body_blocks_steep_rays():
    intensity = np.array([0.05, 0.05, 0.4, 0.4])
    distance = np.array([10.0, 60.0, 10.0, 60.0])
    p = world_scan.return_probability(intensity, distance)
    assert ((p >= 0) & (p <= 1)).all()
    assert p[1] < p[0] and p[3] < p[2] and p[1] < p[3]  # farther and darker: fewer returns
    assert p[0] > 0.99  # a dark car 10 m away always returns
    kitti = get_profile("kitti")
    pattern = world_scan._pattern(kitti)
    blocked = world_scan.ego_blocked(pattern.directions, kitti.mount_height_m)
    elevation = np.degrees(np.arcsin(pattern.directions[:, 2]))
    azimuth = np.degrees(np.arctan2(pattern.directions[:, 1], pattern.directions[:, 0]))
    assert not blocked[elevation > -15.0].any()  # the body is below the sensor, near it
    ahead_steep = (np.abs(azimuth) < 10) & (elevation < -23.0)
    assert blocked[ahead_steep].all()
    waymo = get_profile("waymo")  # mounted higher, beams no steeper than -18 deg: nothing hidden
    assert not world_scan.ego_blocked(world_scan._pattern(waymo).directions, 2.0).any()


def test_world_looks_like_real_kitti_scans_in_front():
    """Against the real KITTI statistics (docs/synth.md: drive 0001 and the object frames, +-40
    deg in front), with wide margins for 6 frames: intensity mostly 0.1-0.4 (not the ground's
    near-zero grazing returns), a few cars in view, points above the ground, dark car returns."""
    from dali_cli.reporting import domains

    kitti = get_profile("kitti")
    rng = np.random.default_rng(0)
    frames = [synth.synth_frame(4, k, kitti, kitti) for k in range(6)]
    stats = domains.summarize(
        [domains.frame_stats(f.points, f.boxes, 80.0, rng) for f in frames]
    ).values
    assert 0.15 <= stats["intensity_median"] <= 0.35 and 0.3 <= stats["intensity_p90"] <= 0.5
    assert 1.0 <= stats["cars_per_frame"] <= 5.0
    assert 15_000 <= stats["points_per_frame"] <= 32_000
    assert -1.73 < stats["height_median_m"] < -1.5  # sidewalks, walls, vegetation lift it
    ground = np.concatenate([f.points[f.owner == -1] for f in frames])
    near = np.hypot(ground[:, 0], ground[:, 1]) < 4.5
    azimuth = np.degrees(np.abs(np.arctan2(ground[:, 1], ground[:, 0])))
    ahead, aside = (near & (azimuth < 20)).sum(), (near & (np.abs(azimuth - 90) < 20)).sum()
    assert ahead < 0.5 * aside  # the ego's hood hides most steep beams ahead, not beside it
    car = np.concatenate([f.points[f.owner >= 0, 3] for f in frames])
    assert np.median(car) < 0.12  # real car returns are dark (median 0.02-0.06)
