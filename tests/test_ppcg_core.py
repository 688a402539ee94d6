"""PPCG building blocks: model selection, box <-> model maps, angular windows, point-model RC."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from ray_reference import hits_and_window_rays, slab_hits

from dali_cli.geometry import inside_boxes
from dali_cli.ppcg.fitting import (
    box_affine,
    box_rng,
    circular_distance,
    model_to_sensor,
    rays_to_model,
    select_cad_models,
    select_point_models,
    sensor_to_model,
    size_cost,
    viewing_angle,
)
from dali_cli.ppcg.inbox import points_per_box
from dali_cli.ppcg.point_models import (
    angular_threshold_rad,
    cast_point_model,
    cast_point_model_bruteforce,
)
from dali_cli.ppcg.window import box_windows, footprint_distances, window_rays
from dali_cli.sensors import get_profile

finite = st.floats(-60, 60, allow_nan=False)
sizes = st.floats(0.3, 8.0, allow_nan=False)
yaws = st.floats(-np.pi, np.pi, allow_nan=False, exclude_max=True)
box_strategy = st.tuples(finite, finite, st.floats(-3, 3), sizes, sizes, sizes, yaws)


def unit_corners() -> np.ndarray:
    return np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])


# ------------------------------------------------------------------------------- placement


@settings(max_examples=40, deadline=None)
@given(box_strategy)
def test_model_frame_round_trip_and_box_fit(box):
    box = np.array(box)
    rng = np.random.default_rng(0)
    points = rng.normal(size=(20, 3)) * 5
    np.testing.assert_allclose(
        model_to_sensor(sensor_to_model(points, box), box), points, atol=1e-9
    )
    # the unit cube lands exactly on the box: local coordinates of its corners are +-l/2, +-w/2, +-h/2
    corners = model_to_sensor(unit_corners(), box)
    cos, sin = np.cos(box[6]), np.sin(box[6])
    offset = corners - box[:3]
    local = np.stack(
        [
            cos * offset[:, 0] + sin * offset[:, 1],
            -sin * offset[:, 0] + cos * offset[:, 1],
            offset[:, 2],
        ],
        1,
    )
    np.testing.assert_allclose(np.abs(local), np.broadcast_to(box[3:6] / 2, (8, 3)), atol=1e-9)


def test_model_scale_is_applied_anisotropically():
    box = np.array([10.0, -4.0, -0.9, 3.0, 1.2, 0.8, 0.7])
    matrix, translation = box_affine(box)
    np.testing.assert_allclose(np.linalg.norm(matrix, axis=0), [3.0, 1.2, 0.8])
    np.testing.assert_allclose(translation, box[:3])
    placed = model_to_sensor(unit_corners(), box)
    extent_along_heading = placed[:, :2] @ np.array([np.cos(0.7), np.sin(0.7)])
    assert np.ptp(extent_along_heading) == pytest.approx(3.0)


@settings(max_examples=30, deadline=None)
@given(box_strategy, st.floats(0.1, 50))
def test_ray_parameter_is_frame_independent(box, parameter):
    box = np.array(box)
    rng = np.random.default_rng(1)
    origins, directions = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    model_origins, model_directions = rays_to_model(origins, directions, box)
    np.testing.assert_allclose(
        model_to_sensor(model_origins + parameter * model_directions, box),
        origins + parameter * directions,
        atol=1e-8 * max(1.0, parameter),
    )


# ------------------------------------------------------------------------------- selection


def test_cad_selection_is_min_size_cost_and_topk_stays_in_the_k_best():
    rng = np.random.default_rng(3)
    model_lwh = rng.uniform([3, 1.4, 1.2], [5.5, 2.1, 1.9], size=(40, 3))
    box_lwh = rng.uniform([3, 1.4, 1.2], [5.5, 2.1, 1.9], size=(12, 3))
    best = select_cad_models(box_lwh, model_lwh)
    for row, lwh in enumerate(box_lwh):
        costs = [sum(abs(m[i] / lwh[i] - 1) for i in range(3)) for m in model_lwh]
        assert best[row] == int(np.argmin(costs))
    rngs = [box_rng(7, "f", i) for i in range(len(box_lwh))]
    picks = select_cad_models(box_lwh, model_lwh, top_k=5, rngs=rngs)
    cost = size_cost(box_lwh, model_lwh)
    fifth = np.sort(cost, axis=1)[:, 4]
    assert (cost[np.arange(len(picks)), picks] <= fifth + 1e-12).all()
    again = select_cad_models(
        box_lwh, model_lwh, top_k=5, rngs=[box_rng(7, "f", i) for i in range(12)]
    )
    np.testing.assert_array_equal(picks, again)
    assert (picks != best).any()  # k > 1 really draws


def test_box_rng_depends_on_seed_frame_and_box_only():
    draw = lambda *key: box_rng(*key).random()  # noqa: E731
    assert draw(0, "000001", 3) == draw(0, "000001", 3)
    assert (
        len(
            {draw(0, "000001", 3), draw(1, "000001", 3), draw(0, "000002", 3), draw(0, "000001", 4)}
        )
        == 4
    )


def test_circular_distance_wraps():
    assert circular_distance(np.pi - 0.1, -np.pi + 0.1) == pytest.approx(0.2)
    assert circular_distance(0.3, 0.3 + 4 * np.pi) == pytest.approx(0.0, abs=1e-12)
    assert circular_distance(0.0, np.pi) == pytest.approx(np.pi)
    # the sensor sees a car driving away from it from behind (pi), an oncoming one from the front (0)
    boxes = np.array(
        [[10, 0, 0, 4, 2, 1.5, 0.0], [10, 0, 0, 4, 2, 1.5, np.pi], [0, 10, 0, 4, 2, 1.5, 0.0]]
    )
    np.testing.assert_allclose(np.abs(viewing_angle(boxes)), [np.pi, 0, np.pi / 2], atol=1e-12)


def test_viewing_angle_matches_the_library_convention():
    from dali_cli.library import point_models_from_frame

    rng = np.random.default_rng(2)
    boxes = np.array(
        [[12.0, -5.0, -0.8, 4.0, 1.8, 1.5, 0.7], [-8.0, 9.0, -0.8, 4.5, 1.9, 1.6, -2.5]]
    )
    local = rng.uniform(-0.5, 0.5, size=(400, 3))
    points = np.concatenate([model_to_sensor(local, box) for box in boxes])
    points = np.concatenate([points, np.zeros((len(points), 1))], axis=1).astype(np.float32)
    models = point_models_from_frame(points, boxes, "f", min_points=300)
    np.testing.assert_allclose(
        circular_distance(models.view_angle_rad, viewing_angle(boxes)), 0, atol=1e-9
    )


def test_point_model_selection_matches_bruteforce():
    rng = np.random.default_rng(5)
    model_angle = rng.uniform(-np.pi, np.pi, 300)
    model_lwh = rng.uniform([3, 1.4, 1.2], [5.5, 2.1, 1.9], size=(300, 3))
    box_angle = np.r_[rng.uniform(-np.pi, np.pi, 30), np.pi - 1e-4, -np.pi]
    box_lwh = rng.uniform([3, 1.4, 1.2], [5.5, 2.1, 1.9], size=(32, 3))
    tolerance = np.radians(4.0)
    picks = select_point_models(box_angle, box_lwh, model_angle, model_lwh, tolerance)
    for row in range(len(box_angle)):
        distance = circular_distance(model_angle, box_angle[row])
        candidates = np.flatnonzero(distance <= distance.min() + tolerance + 1e-9)
        costs = size_cost(box_lwh[row], model_lwh[candidates])[0]
        assert picks[row] == candidates[np.argmin(costs)]


# ------------------------------------------------------------------------------- windows


def surface_samples(box: np.ndarray, count: int, rng) -> np.ndarray:
    local = rng.uniform(-0.5, 0.5, size=(count, 3))
    axis = rng.integers(0, 3, count)
    local[np.arange(count), axis] = np.sign(local[np.arange(count), axis]) * 0.5
    return model_to_sensor(local, box)


def test_window_contains_every_box_point_and_is_tight():
    rng = np.random.default_rng(11)
    boxes = np.array(
        [
            [6.0, 0.0, -0.9, 1.8, 4.5, 1.5, 0.0],  # side-on car at 6 m, straight ahead
            [-20.0, 0.3, -0.8, 4.0, 1.8, 1.5, 0.3],  # across the azimuth seam at +-pi
            [3.0, 4.0, 1.5, 4.0, 1.8, 1.0, 1.0],  # entirely above the sensor
            [30.0, -12.0, -3.0, 4.2, 1.9, 1.4, -2.0],  # entirely below the sensor
        ]
    )
    windows = box_windows(boxes)
    for index, box in enumerate(boxes):
        points = surface_samples(box, 40000, rng)
        azimuth = np.arctan2(points[:, 1], points[:, 0])
        elevation = np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]))
        lo, hi = windows.azimuth_lo[index], windows.azimuth_hi[index]
        relative = np.mod(azimuth - lo, 2 * np.pi)
        assert (relative <= hi - lo).all()
        assert (elevation >= windows.elevation_lo[index]).all()
        assert (elevation <= windows.elevation_hi[index]).all()
        # tight: samples come close to every bound
        assert relative.max() > hi - lo - 5e-3 and relative.min() < 5e-3
        assert elevation.min() < windows.elevation_lo[index] + 5e-3
        assert elevation.max() > windows.elevation_hi[index] - 5e-3


def test_window_selects_every_ray_that_can_hit_the_box():
    profile = get_profile("kitti")
    directions = profile.ray_pattern().directions.astype(np.float64)
    boxes = np.array([[6.0, 0.0, -0.9, 1.8, 4.5, 1.5, 0.0], [-20.0, 0.3, -0.8, 4.0, 1.8, 1.5, 0.3]])
    windows = box_windows(boxes)
    for _, _, hits, rays in hits_and_window_rays(profile, boxes):
        assert len(hits) > 100
        assert np.isin(hits, rays.index).all()
        np.testing.assert_allclose(rays.directions, directions[rays.index], atol=1e-6)
        assert len(rays.index) < 3 * len(hits)  # the window does not scan far beyond the box
    # the nearest footprint point of the side-on car is mid-edge, not a corner
    near, _ = footprint_distances(boxes[:1])
    assert near[0] == pytest.approx(5.1)
    corner_distance = np.hypot(5.1, 2.25)
    top = boxes[0, 2] + 0.75
    bottom = boxes[0, 2] - 0.75
    corner_rays = window_rays(
        profile,
        windows.azimuth_lo[0],
        windows.azimuth_hi[0],
        np.arctan2(bottom, corner_distance),
        np.arctan2(top, corner_distance),
    )
    hits = np.flatnonzero(slab_hits(directions, boxes[0]))
    assert not np.isin(hits, corner_rays.index).all()  # corners alone would lose hits


@settings(max_examples=60, deadline=None)
@given(
    st.floats(-np.pi, np.pi, exclude_max=True),
    st.floats(0.0, 0.5),
    st.floats(-0.5, 0.1),
    st.floats(0, 0.3),
)
def test_window_rays_equal_a_scan_of_the_full_pattern(
    azimuth_lo, span, elevation_lo, elevation_span
):
    profile = get_profile("nuscenes")
    elevation_hi = elevation_lo + elevation_span
    rays = window_rays(profile, azimuth_lo, azimuth_lo + span, elevation_lo, elevation_hi)
    grid_elevation, grid_azimuth = np.meshgrid(
        profile.elevations_rad(), profile.azimuths_rad(), indexing="ij"
    )  # (B, P), beam-major like the RayPattern
    relative = np.mod(grid_azimuth - azimuth_lo, 2 * np.pi).ravel()
    grid_elevation = grid_elevation.ravel()
    inside = (
        (relative <= span) & (grid_elevation >= elevation_lo) & (grid_elevation <= elevation_hi)
    )
    on_edge = (
        np.isclose(relative, 0.0, atol=1e-9)
        | np.isclose(relative, span, atol=1e-9)
        | np.isclose(relative, 2 * np.pi, atol=1e-9)
        | np.isclose(grid_elevation, elevation_lo, atol=1e-9)
        | np.isclose(grid_elevation, elevation_hi, atol=1e-9)
    )
    selected = np.zeros(len(inside), bool)
    selected[rays.index] = True
    assert len(np.unique(rays.index)) == len(rays.index)
    assert not ((selected != inside) & ~on_edge).any()


# ------------------------------------------------------------------------------- point models


@pytest.mark.parametrize("seed", range(6))
def test_point_model_cast_equals_bruteforce(seed):
    """Random clouds and rays around a car-sized blob; both hits and misses occur."""
    rng = np.random.default_rng(seed)
    theta = angular_threshold_rad(781) * rng.uniform(0.5, 3.0)
    centre = np.array([rng.uniform(5, 40), rng.uniform(-10, 10), rng.uniform(-1.5, 0)])
    model = centre + rng.normal(size=(rng.integers(1, 400), 3)) * [1.5, 0.8, 0.5]
    if seed % 2:  # duplicate ranges: ties go to the lower index in both
        model = np.concatenate([model, model[::-1]])
    directions = centre + rng.normal(size=(rng.integers(1, 300), 3)) * [1.8, 1.0, 0.6]
    directions = np.concatenate([directions, rng.normal(size=(20, 3))])  # mostly misses
    origin = np.zeros(3) if seed < 3 else rng.normal(size=3)
    fast = cast_point_model(origin, directions, model, theta)
    slow = cast_point_model_bruteforce(origin, directions, model, theta)
    np.testing.assert_array_equal(fast.model_index, slow.model_index)
    np.testing.assert_array_equal(fast.hit, slow.hit)
    np.testing.assert_allclose(fast.distance[fast.hit], slow.distance[slow.hit])
    assert fast.hit.any() and (~fast.hit).any()
    # hits lie on their ray, at the range of the chosen model point
    unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    offset = fast.points[fast.hit] - origin
    cross = np.linalg.norm(np.cross(offset, unit[fast.hit]), axis=1) / np.linalg.norm(
        offset, axis=1
    )
    assert (cross < 1e-9).all()
    np.testing.assert_allclose(
        np.linalg.norm(offset, axis=1),
        np.linalg.norm(model[fast.model_index[fast.hit]] - origin, axis=1),
    )


def test_point_model_cast_handles_empty_inputs():
    empty = cast_point_model(np.zeros(3), np.zeros((0, 3)), np.ones((5, 3)), 0.01)
    assert empty.hit.shape == (0,)
    no_model = cast_point_model(np.zeros(3), np.ones((4, 3)), np.zeros((0, 3)), 0.01)
    assert not no_model.hit.any() and np.isinf(no_model.distance).all()


# ------------------------------------------------------------------------------- in-box points


def random_boxes(rng, k: int, *, xy_m: float, z_m, size_m, yaw: float) -> np.ndarray:
    """`k` boxes `(k, 7)`: x, y uniform in [-xy_m, xy_m], z in `z_m`, each of l, w, h in `size_m`
    (m), yaw in [-yaw, yaw] (rad)."""
    return np.concatenate(
        [
            rng.uniform(-xy_m, xy_m, (k, 2)),
            rng.uniform(*z_m, (k, 1)),
            rng.uniform(*size_m, (k, 3)),
            rng.uniform(-yaw, yaw, (k, 1)),
        ],
        1,
    )


@pytest.mark.parametrize("seed", range(8))
def test_points_per_box_equals_bruteforce(seed):
    rng = np.random.default_rng(seed)
    count = 20000
    points = np.concatenate(
        [
            rng.uniform(-30, 30, (count, 2)),
            rng.uniform(-2, 1, (count, 1)),
            rng.uniform(0, 1, (count, 1)),
        ],
        1,
    ).astype(np.float32)
    k = int(rng.integers(1, 20))
    boxes = random_boxes(rng, k, xy_m=35, z_m=(-1, 0), size_m=(0.5, 6), yaw=4)
    boxes = np.concatenate([boxes, boxes[:1] + [0.5, 0, 0, 0, 0, 0, 0.3]])  # an overlapping pair
    margin = float(rng.uniform(0, 0.5))
    result = points_per_box(points, boxes, margin)
    claimed = np.zeros(count, bool)
    for box, got in zip(boxes, result, strict=True):
        local = sensor_to_model(points[:, :3].astype(np.float64), box) * box[3:6]
        inside = (np.abs(local) <= box[3:6] / 2 + margin + 1e-9).all(axis=1) & ~claimed
        claimed |= inside
        np.testing.assert_array_equal(got, np.flatnonzero(inside))
    assert claimed.sum() > 0


@pytest.mark.parametrize("seed", range(4))
def test_points_per_box_agrees_with_inside_boxes_on_the_faces(seed):
    """Points within float32 rounding of the faces (of overlapping boxes too): the grouped test
    decides every point exactly as geometry.inside_boxes does in float32, first box winning."""
    rng = np.random.default_rng(seed)
    k = 12
    boxes = random_boxes(rng, k, xy_m=60, z_m=(-1.5, 0), size_m=(0.3, 8), yaw=np.pi)
    boxes = np.concatenate([boxes, boxes[:3] + [0.4, -0.2, 0, 0, 0, 0, 0.5]])  # overlaps
    # points on each box's faces (unit-cube surface in box coordinates), nudged by ~float32 ulps
    per_box = 3000
    local = rng.uniform(-0.5, 0.5, (len(boxes), per_box, 3))
    axis = rng.integers(0, 3, (len(boxes), per_box))
    np.put_along_axis(local, axis[..., None], rng.choice([-0.5, 0.5], (len(boxes), per_box, 1)), 2)
    scaled = local * boxes[:, None, 3:6]
    cos, sin = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    xyz = np.stack(
        [
            boxes[:, 0:1] + cos * scaled[..., 0] - sin * scaled[..., 1],
            boxes[:, 1:2] + sin * scaled[..., 0] + cos * scaled[..., 1],
            boxes[:, 2:3] + scaled[..., 2],
        ],
        -1,
    ).reshape(-1, 3)
    xyz += rng.normal(0, 2e-6, xyz.shape) * np.abs(xyz).max(axis=1, keepdims=True)
    points = np.concatenate([xyz, rng.uniform(0, 1, (len(xyz), 1))], 1).astype(np.float32)
    margin = [0.0, 0.1][seed % 2]
    result = points_per_box(points, boxes, margin)
    claimed = np.zeros(len(points), bool)
    decided_both_ways = 0
    for box, got in zip(boxes, result, strict=True):
        inside = inside_boxes(points, box, margin)
        decided_both_ways += int(inside.sum() > 0 and (~inside).sum() > 0)
        expected = inside & ~claimed
        claimed |= expected
        np.testing.assert_array_equal(got, np.flatnonzero(expected))
    assert decided_both_ways == len(boxes)  # the faces split points on both sides for every box
