"""Box geometry: IoU against shapely, IoU properties, degenerate boxes, points in boxes, NMS,
ground-frame scaling."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import Polygon

from dali_cli import geometry as g


def random_boxes(rng: np.random.Generator, n: int, spread: float = 5.0) -> np.ndarray:
    centre = rng.uniform(-spread, spread, (n, 3))
    size = rng.uniform(0.2, 6.0, (n, 3))
    yaw = rng.uniform(-4.0, 4.0, n)
    return np.c_[centre, size, yaw]


def shapely_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    corners_a, corners_b = g.bev_corners(a), g.bev_corners(b)
    result = np.empty(len(a))
    for k in range(len(a)):
        pa, pb = Polygon(corners_a[k]), Polygon(corners_b[k])
        inter = pa.intersection(pb).area
        union = pa.area + pb.area - inter
        result[k] = inter / union if union > 0 else 0.0
    return result


def test_bev_iou_matches_shapely_on_random_pairs():
    rng = np.random.default_rng(0)
    a = random_boxes(rng, 12_000)
    b = random_boxes(rng, 12_000)
    b[:, :2] = a[:, :2] + rng.uniform(-3, 3, (len(a), 2))  # most pairs overlap
    ours = g.bev_iou_pairs(a, b)
    reference = shapely_iou(a, b)
    assert (reference > 0).mean() > 0.5
    assert np.abs(ours - reference).max() <= 1e-9


def test_bev_iou_matches_shapely_far_from_origin_and_aligned():
    rng = np.random.default_rng(1)
    a = random_boxes(rng, 2000)
    b = a.copy()
    b[:, :2] += rng.uniform(-2, 2, (len(a), 2))
    b[:, 6] = a[:, 6] + rng.choice([0.0, np.pi / 2, np.pi, -np.pi / 2], len(a))  # parallel edges
    expected = shapely_iou(a, b)  # computed near the origin, where float64 is exact enough
    shift = np.array([1e4, -1e4, 0.0])
    far_a, far_b = a.copy(), b.copy()
    far_a[:, :3] += shift
    far_b[:, :3] += shift
    assert np.abs(g.bev_iou_pairs(far_a, far_b) - expected).max() <= 1e-9


def test_bev_iou_reads_no_uninitialized_memory(monkeypatch):
    """Memory numpy leaves uninitialized (np.empty_like) is filled with inf here: the clipping must
    neither read it into a result nor warn about it (uninitialized slots past a polygon's last
    vertex made `dali compare` print "invalid value encountered in multiply" now and then)."""
    rng = np.random.default_rng(2)
    a = random_boxes(rng, 3000)
    b = random_boxes(rng, 3000)
    b[:, :2] = a[:, :2] + rng.uniform(-3, 3, (len(a), 2))
    clean = g.bev_iou_pairs(a, b)
    real_empty_like = np.empty_like

    def poisoned_empty_like(prototype, *args, **kwargs):
        out = real_empty_like(prototype, *args, **kwargs)
        if out.dtype.kind in "fc":
            out.fill(np.inf)  # inf, not NaN: inf * 0 raises the invalid flag, NaN propagates
        return out

    monkeypatch.setattr(np, "empty_like", poisoned_empty_like)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        poisoned = g.bev_iou_pairs(a, b)
    np.testing.assert_array_equal(poisoned, clean)
    assert np.abs(clean - shapely_iou(a, b)).max() <= 1e-9


@pytest.mark.parametrize(
    "a, b, expected",
    [
        # identical, and the same rectangle described rotated by 90 and 180 degrees
        ([0, 0, 0, 4, 2, 1, 0.3], [0, 0, 0, 4, 2, 1, 0.3], 1.0),
        ([0, 0, 0, 4, 2, 1, 0.0], [0, 0, 0, 2, 4, 1, np.pi / 2], 1.0),
        ([0, 0, 0, 4, 2, 1, 0.0], [0, 0, 0, 4, 2, 1, np.pi], 1.0),
        ([0, 0, 0, 4, 2, 1, 0.0], [0, 0, 0, 4, 2, 1, -np.pi], 1.0),
        # coincident edges: side by side (touching), half shifted, nested with a shared edge
        ([0, 0, 0, 2, 2, 1, 0.0], [2, 0, 0, 2, 2, 1, 0.0], 0.0),
        ([0, 0, 0, 2, 2, 1, 0.0], [1, 0, 0, 2, 2, 1, 0.0], 2 / 6),
        ([0, 0, 0, 2, 2, 1, 0.0], [0.5, 0, 0, 1, 2, 1, 0.0], 0.5),
        ([0, 0, 0, 2, 2, 1, 0.0], [1, 1, 0, 2, 2, 1, 0.0], 1 / 7),
        # corner touching corner, and a box rotated 45 degrees inside a large one
        ([0, 0, 0, 2, 2, 1, 0.0], [2, 2, 0, 2, 2, 1, 0.0], 0.0),
        ([0, 0, 0, 10, 10, 1, 0.0], [0, 0, 0, 2, 2, 1, np.pi / 4], 4 / 100),
        # zero-size boxes: no NaN, IoU 0
        ([0, 0, 0, 0, 0, 0, 0.0], [0, 0, 0, 0, 0, 0, 0.0], 0.0),
        ([0, 0, 0, 0, 2, 1, 0.0], [0, 0, 0, 2, 2, 1, 0.0], 0.0),
        ([0, 0, 0, 2, 2, 1, 0.0], [0, 0, 0, 2, 0, 1, 0.7], 0.0),
        # far coordinates
        ([1e4, -1e4, 0, 4, 2, 1, 0.0], [1e4 + 1, -1e4, 0, 4, 2, 1, 0.0], 6 / 10),
    ],
)
def test_bev_iou_degenerate_cases(a, b, expected):
    a, b = np.array([a], float), np.array([b], float)
    for first, second in ((a, b), (b, a)):
        iou = g.bev_iou_pairs(first, second)
        assert np.isfinite(iou).all()
        assert iou[0] == pytest.approx(expected, abs=1e-12)
        assert g.bev_iou(first, second)[0, 0] == pytest.approx(expected, abs=1e-12)


def test_pairwise_matrices_agree_with_row_wise():
    rng = np.random.default_rng(2)
    a, b = random_boxes(rng, 40, spread=4), random_boxes(rng, 30, spread=4)
    matrix = g.bev_iou(a, b)
    i, j = np.meshgrid(np.arange(40), np.arange(30), indexing="ij")
    assert matrix.shape == (40, 30)
    assert (matrix > 0).sum() > 50
    np.testing.assert_allclose(
        matrix.ravel(), g.bev_iou_pairs(a[i.ravel()], b[j.ravel()]), atol=1e-15
    )
    np.testing.assert_allclose(
        g.iou_3d(a, b).ravel(), g.iou_3d_pairs(a[i.ravel()], b[j.ravel()]), atol=1e-15
    )


def test_iou_3d_is_bev_intersection_times_height_overlap():
    a = np.array([[0, 0, 0.0, 4, 2, 2, 0.0]])
    b = np.array([[1, 0, 1.0, 4, 2, 2, 0.0]])  # BEV overlap 3 x 2, height overlap 1
    assert g.iou_3d(a, b)[0, 0] == pytest.approx(6 / (16 + 16 - 6))
    c = np.array([[0, 0, 2.0, 4, 2, 2, 0.0]])  # stacked on top: touching faces
    assert g.iou_3d(a, c)[0, 0] == 0.0
    assert g.bev_iou(a, c)[0, 0] == 1.0


finite = st.floats(-50, 50, allow_nan=False)
sizes = st.floats(0.05, 8, allow_nan=False)
angles = st.floats(-10, 10, allow_nan=False)
box_strategy = st.tuples(finite, finite, st.floats(-2, 2), sizes, sizes, sizes, angles)


@settings(max_examples=150, deadline=None)
@given(
    box_strategy,
    st.tuples(st.floats(-4, 4), st.floats(-4, 4), st.floats(-1, 1)),
    st.tuples(sizes, sizes, sizes, angles),
    angles,
    st.tuples(finite, finite),
)
def test_iou_properties(box_a, delta, shape_b, turn, shift):
    a = np.array([box_a], float)
    b = np.array([[a[0, 0] + delta[0], a[0, 1] + delta[1], a[0, 2] + delta[2], *shape_b]])
    iou_ab, iou_ba = g.bev_iou_pairs(a, b)[0], g.bev_iou_pairs(b, a)[0]
    assert 0.0 <= iou_ab <= 1.0
    assert iou_ab == pytest.approx(iou_ba, abs=1e-12)
    assert g.bev_iou_pairs(a, a)[0] == 1.0
    assert g.iou_3d_pairs(a, a)[0] == 1.0
    iou3 = g.iou_3d_pairs(a, b)[0]
    assert 0.0 <= iou3 <= 1.0 and iou3 == pytest.approx(g.iou_3d_pairs(b, a)[0], abs=1e-12)

    # the same rigid motion applied to both boxes leaves both IoUs unchanged
    def move(box):
        moved = box.copy()
        rotation = g.rotation_z(turn)
        moved[:, :3] = moved[:, :3] @ rotation.T + np.array([shift[0], shift[1], 0.0])
        moved[:, 6] = g.wrap_angle(moved[:, 6] + turn)
        return moved

    assert g.bev_iou_pairs(move(a), move(b))[0] == pytest.approx(iou_ab, abs=1e-9)
    assert g.iou_3d_pairs(move(a), move(b))[0] == pytest.approx(iou3, abs=1e-9)


def test_wrap_angle_range_and_equivalence():
    yaw = np.array([-np.pi, np.pi, 3 * np.pi, -1e-20, 7.0, -7.0, 0.0, np.nextafter(np.pi, 0)])
    wrapped = g.wrap_angle(yaw)
    assert ((wrapped >= -np.pi) & (wrapped < np.pi)).all()
    np.testing.assert_allclose(np.cos(wrapped), np.cos(yaw), atol=1e-12)
    np.testing.assert_allclose(np.sin(wrapped), np.sin(yaw), atol=1e-12)
    assert g.wrap_angle(np.pi) == -np.pi
    assert isinstance(g.wrap_angle(4.0), float)


def test_rotation_and_corners():
    assert g.rotation_z(0.3).shape == (3, 3)
    stack = g.rotation_z(np.array([0.0, np.pi / 2]))
    assert stack.shape == (2, 3, 3)
    np.testing.assert_allclose(stack[1] @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    box = np.array([[1.0, 2.0, 3.0, 4.0, 2.0, 1.0, np.pi / 2]])
    corners = g.box_corners(box)
    assert corners.shape == (1, 8, 3)
    np.testing.assert_allclose(corners[0].mean(axis=0), box[0, :3])
    np.testing.assert_allclose(corners[0, :4, 2], 2.5)
    np.testing.assert_allclose(corners[0, 4:, 2], 3.5)
    bev = g.bev_corners(box)[0]
    # counter-clockwise: positive shoelace area equal to l * w; first corner is front-left
    area = 0.5 * sum(
        bev[k, 0] * bev[(k + 1) % 4, 1] - bev[(k + 1) % 4, 0] * bev[k, 1] for k in range(4)
    )
    assert area == pytest.approx(8.0)
    np.testing.assert_allclose(bev[0], [1 - 1, 2 + 2], atol=1e-12)
    # corners lie on the boundary (inside, boundaries included); pushed outwards they leave it
    assert g.inside_boxes(corners[0], box[0], margin_m=1e-9).all()
    outward = box[0, :3] + (corners[0] - box[0, :3]) * 1.01
    assert not g.inside_boxes(outward, box[0]).any()
    # float32 frames are tested in float32, with the same answer away from the boundary
    assert (g.inside_boxes(corners[0].astype(np.float32), box[0], 1e-3)).all()


def to_box_frame(points: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Reference: points `(M, >=3)` in the box's frame `(M, 3)` by an explicit rotation matrix."""
    return (points[:, :3] - box[:3]) @ g.rotation_z(box[6])


def test_points_in_boxes_grid_matches_brute_force():
    rng = np.random.default_rng(3)
    boxes = random_boxes(rng, 60, spread=20)
    boxes[:3] = boxes[3]  # identical overlapping boxes: the first index wins
    points = np.c_[
        rng.uniform(-25, 25, (20_000, 2)), rng.uniform(-5, 5, 20_000), rng.uniform(0, 1, 20_000)
    ]
    for margin in (0.0, 0.3):
        local = np.stack([to_box_frame(points, box) for box in boxes], axis=1)  # (M, N, 3)
        inside = (np.abs(local) <= boxes[None, :, 3:6] / 2 + margin).all(axis=2)  # (M, N)
        expected = np.where(inside.any(axis=1), inside.argmax(axis=1), -1)
        indices = g.point_box_indices(points, boxes, margin_m=margin)
        assert indices.dtype == np.int64
        np.testing.assert_array_equal(indices, expected)
        counts = g.count_points_in_boxes(points, boxes, margin_m=margin)
        assert counts.dtype == np.int32
        np.testing.assert_array_equal(counts, inside.sum(axis=0))
    indices = g.point_box_indices(points, boxes)
    assert (indices == 0).sum() > 0 and np.isin(indices, [1, 2, 3]).sum() == 0
    assert g.point_box_indices(points, np.zeros((0, 7))).tolist() == [-1] * len(points)
    assert g.count_points_in_boxes(np.zeros((0, 3)), boxes).tolist() == [0] * len(boxes)


def test_nms_keeps_best_and_suppresses_strictly_above_threshold():
    base = np.array([0, 0, 0, 4, 2, 1.5, 0.0])
    shifted = base + [1, 0, 0, 0, 0, 0, 0]  # IoU 3/5 = 0.6 with base
    far = base + [20, 0, 0, 0, 0, 0, 0]
    boxes = np.stack([shifted, base, far, base])
    scores = np.array([0.8, 0.9, 0.5, 0.7])
    assert g.nms_bev(boxes, scores, 0.5).tolist() == [1, 2]
    assert g.nms_bev(boxes, scores, 0.6).tolist() == [1, 0, 2]  # 0.6 is not > 0.6
    assert g.nms_bev(boxes, scores, 1.0).tolist() == [1, 0, 3, 2]
    assert g.nms_bev(np.zeros((0, 7)), np.zeros(0), 0.5).tolist() == []


def test_nms_matches_dense_greedy_reference():
    rng = np.random.default_rng(4)
    boxes = random_boxes(rng, 300, spread=15)
    scores = rng.uniform(size=300)
    iou = g.bev_iou(boxes, boxes)
    order = np.argsort(-scores, kind="stable")
    alive = np.ones(300, bool)
    expected = []
    for index in order:
        if alive[index]:
            expected.append(index)
            alive &= ~(iou[index] > 0.3)
    assert g.nms_bev(boxes, scores, 0.3).tolist() == expected


def test_ground_frame_shift_and_scaling_round_trip():
    rng = np.random.default_rng(5)
    points = rng.normal(size=(100, 4)).astype(np.float32)
    mount = 1.73
    ground = g.sensor_to_ground(points, mount)
    np.testing.assert_allclose(ground[:, 2], points[:, 2] + mount, rtol=1e-6)
    np.testing.assert_allclose(g.ground_to_sensor(ground, mount), points, atol=1e-6)
    scaled = g.scale_points_about_ground(points, 1.2, mount)
    assert scaled.dtype == np.float32
    np.testing.assert_array_equal(scaled[:, 3], points[:, 3])
    # a point on the ground stays on the ground; the sensor origin moves up with the scale
    on_ground = np.array([[5.0, 2.0, -mount, 0.5]])
    np.testing.assert_allclose(
        g.scale_points_about_ground(on_ground, 1.5, mount)[0, :3], [7.5, 3.0, -mount]
    )
    boxes = random_boxes(rng, 20)
    scaled_boxes = g.scale_boxes_about_ground(boxes, 0.8, mount)
    np.testing.assert_allclose(scaled_boxes[:, 3:6], boxes[:, 3:6] * 0.8)
    np.testing.assert_array_equal(scaled_boxes[:, 6], boxes[:, 6])
    np.testing.assert_allclose(
        g.descale_boxes_about_ground(scaled_boxes, 0.8, mount), boxes, atol=1e-12
    )
    # points inside a box stay inside it when both are scaled the same way
    box = np.array([[10.0, 3.0, -mount + 0.75, 4.0, 2.0, 1.5, 0.4]])
    local = rng.uniform(-0.5, 0.5, (50, 3)) * [3.5, 1.5, 1.2]
    inside = local @ g.rotation_z(0.4).T + box[0, :3]
    inside = np.c_[inside, np.zeros(50)]
    assert (g.point_box_indices(inside, box) == 0).all()
    assert (
        g.point_box_indices(
            g.scale_points_about_ground(inside, 1.3, mount),
            g.scale_boxes_about_ground(box, 1.3, mount),
        )
        == 0
    ).all()
    assert math.isclose(g.scale_boxes_about_ground(box, 2.0, mount)[0, 2] - 0.75 * 2, -mount)


@pytest.mark.parametrize("margin_m", [0.0, 0.3])
def test_point_box_pairs_equal_every_pair_tested(margin_m: float) -> None:
    """The grid-candidate search finds exactly the (point, box) containments of the all-pairs test,
    overlapping boxes included, with point indices ascending and box indices ascending per point."""
    rng = np.random.default_rng(7)
    boxes = random_boxes(rng, 40, spread=12.0)
    points = rng.uniform(-16.0, 16.0, (5000, 4)).astype(np.float32)
    point_index, box_index = g.point_box_pairs(points, boxes, margin_m)
    every = g.inside_boxes(  # (M, N) by broadcasting each point against each box
        points[:, None, :3].astype(np.float64), boxes[None, :, :], margin_m
    )
    want_point, want_box = np.nonzero(every)  # row-major: points ascending, boxes within a point
    assert len(want_point) > 100  # overlaps and misses both occur at this density
    assert np.array_equal(point_index, want_point)
    assert np.array_equal(box_index, want_box)


def test_shrink_boxes_moves_each_face_in_by_the_slack_and_keeps_the_bottom():
    boxes = np.array([[10.0, -3.0, -1.0, 4.0, 1.8, 1.5, 0.7], [1.0, 2.0, 0.0, 0.1, 0.1, 0.1, -2.0]])
    inner = g.shrink_boxes(boxes, [0.05, 0.02, 0.04])
    np.testing.assert_allclose(inner[0, 3:6], [3.9, 1.76, 1.46])
    np.testing.assert_allclose(inner[:, [0, 1, 6]], boxes[:, [0, 1, 6]])  # same place, heading
    bottom = lambda b: b[:, 2] - b[:, 5] / 2  # noqa: E731
    np.testing.assert_allclose(bottom(inner), bottom(boxes))
    np.testing.assert_allclose(inner[1, 3:6], [0.05, 0.06, 0.06])  # never below half a size
    for corners, box in zip(g.box_corners(inner), boxes, strict=True):
        assert g.inside_boxes(corners, box, 1e-9).all()
