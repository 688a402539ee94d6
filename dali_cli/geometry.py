"""Box geometry: corners, rigid transforms, points in boxes, rotated BEV/3D IoU and BEV NMS.

Boxes are `(N, 7)` float64 `x, y, z, l, w, h, yaw` (geometric centre, l along the heading, yaw CCW
from +x); points are `(M, >=3)` in the same frame. Overlaps are computed in float64 by clipping one
rectangle against the other (Sutherland-Hodgman), vectorized over all box pairs at once, in the
second box's frame (built from centre differences, so far-away boxes at 1e4 m keep full precision).
"""

from __future__ import annotations

import numpy as np

# Local BEV corner signs, counter-clockwise: front-left, rear-left, rear-right, front-right.
_BEV_SIGNS = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]])
_PAIR_BLOCK = 1 << 14  # pairs clipped per block: bounds temporary memory to a few tens of MB


# ---------------------------------------------------------------------------------------------
# Angles, rotations, corners


def wrap_angle(angle: float | np.ndarray) -> float | np.ndarray:
    """Angles (rad) wrapped into [-pi, pi): the one yaw wrapping of dali.

    Float arrays keep their dtype (a float32 yaw column stays float32, computed in float32);
    integers become float64; scalars stay scalars, arrays keep their shape.
    """
    array = np.asarray(angle)
    if not np.issubdtype(array.dtype, np.floating):
        array = array.astype(np.float64)
    wrapped = np.mod(array + np.pi, 2.0 * np.pi) - np.pi
    # np.mod can round up to exactly 2 pi for tiny negative inputs, which would give +pi
    wrapped = np.where(wrapped >= np.pi, wrapped - 2.0 * np.pi, wrapped)
    return float(wrapped) if np.ndim(angle) == 0 else wrapped


def rotation_z(yaw: float | np.ndarray) -> np.ndarray:
    """Rotation about +z by `yaw` (rad): `(3, 3)` for a scalar, `(N, 3, 3)` for an `(N,)` array."""
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    zero, one = np.zeros_like(yaw), np.ones_like(yaw)
    matrix = np.stack([c, -s, zero, s, c, zero, zero, zero, one], axis=-1)  # (..., 9)
    return matrix.reshape(yaw.shape + (3, 3))


def _as_boxes(boxes: np.ndarray) -> np.ndarray:
    boxes = np.asarray(boxes, dtype=np.float64)
    if boxes.ndim == 1:
        boxes = boxes.reshape(1, -1)
    if boxes.ndim != 2 or boxes.shape[1] != 7:
        raise ValueError(f"boxes must be (N, 7), got {boxes.shape}")
    return boxes


def rotate_xy(xy: np.ndarray, angle: float) -> np.ndarray:
    """`(..., 2)` x, y rotated counter-clockwise by `angle` (rad) about the origin."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * xy[..., 0] - s * xy[..., 1], s * xy[..., 0] + c * xy[..., 1]], axis=-1)


def bev_corners(boxes: np.ndarray) -> np.ndarray:
    """BEV rectangle corners `(N, 4, 2)` float64, counter-clockwise, of `(N, 7)` boxes."""
    boxes = _as_boxes(boxes)
    local = _BEV_SIGNS[None] * boxes[:, None, 3:5]  # (N, 4, 2)
    c, s = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]  # (N, 1)
    x = c * local[..., 0] - s * local[..., 1] + boxes[:, None, 0]
    y = s * local[..., 0] + c * local[..., 1] + boxes[:, None, 1]
    return np.stack([x, y], axis=-1)


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """Corners `(N, 8, 3)` float64: the bottom face CCW (as bev_corners), then the top face."""
    boxes = _as_boxes(boxes)
    bev = bev_corners(boxes)  # (N, 4, 2)
    bottom = (boxes[:, 2] - boxes[:, 5] / 2)[:, None, None] * np.ones((1, 4, 1))
    top = (boxes[:, 2] + boxes[:, 5] / 2)[:, None, None] * np.ones((1, 4, 1))
    return np.concatenate(
        [np.concatenate([bev, bottom], axis=2), np.concatenate([bev, top], axis=2)], axis=1
    )


def shrink_boxes(boxes: np.ndarray, slack_m: np.ndarray) -> np.ndarray:
    """Boxes `(N, 7)` drawn with room to spare -> the boxes `(N, 7)` float64 of what they hold:
    each end and each side face moves inwards by slack_m `(3,)` (l, w, h; metres), the top face
    by slack_m[2], the bottom stays (a car stands on the ground). No size shrinks below half."""
    slack = np.asarray(slack_m, dtype=np.float64).reshape(3)
    inner = _as_boxes(boxes).astype(np.float64, copy=True)
    outer = inner[:, 3:6].copy()
    inner[:, 3:6] = np.maximum(outer - slack * [2.0, 2.0, 1.0], 0.5 * outer)
    inner[:, 2] -= 0.5 * (outer[:, 2] - inner[:, 5])
    return inner


def footprints_overlap(candidate: np.ndarray, others: np.ndarray) -> np.ndarray:
    """Separating-axis test of one footprint `(4, 2)` against many `(M, 4, 2)` → `(M,)` bool."""
    if len(others) == 0:
        return np.zeros(0, bool)
    cand_edges = np.diff(candidate[[0, 1, 2]], axis=0)  # (2, 2)
    other_edges = others[:, 1:3] - others[:, 0:2]  # (M, 2, 2)
    axes = np.concatenate([np.broadcast_to(cand_edges, other_edges.shape), other_edges], axis=1)
    axes = np.stack([-axes[..., 1], axes[..., 0]], axis=-1)  # (M, 4, 2) edge normals
    project_candidate = np.einsum("mak,ck->mac", axes, candidate)  # (M, 4, 4)
    project_others = np.einsum("mak,mck->mac", axes, others)  # (M, 4, 4)
    separated = (project_candidate.max(-1) < project_others.min(-1)) | (
        project_others.max(-1) < project_candidate.min(-1)
    )
    return ~separated.any(axis=1)


# ---------------------------------------------------------------------------------------------
# Points in boxes


def points_in_box_frames(xyz: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Points `(M, >=3)` into the frames of per-point boxes `(M, 7)` → `(M, 3)` float64 (metres,
    unscaled: x along the box's heading, z up from its centre)."""
    offset = np.asarray(xyz, np.float64)[:, :3] - boxes[:, :3]
    cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    return np.stack(
        [
            cos * offset[:, 0] + sin * offset[:, 1],
            -sin * offset[:, 0] + cos * offset[:, 1],
            offset[:, 2],
        ],
        axis=1,
    )


def inside_boxes(points: np.ndarray, boxes: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
    """Row-wise containment: is points[k] `(K, >=3)` inside boxes[k] `(K, 7)` (or every point in
    one box `(7,)`), grown by `margin_m` on each side, boundaries included? -> `(K,)` bool.

    Computed in the points' float dtype (float32 frames are tested in float32, the box's
    parameters rounded to it), so callers that cast nothing pay no float64 copy of a frame.
    """
    return inside_box_frames(points[..., :3], *box_frames(boxes, margin_m, points.dtype))


def box_frames(boxes: np.ndarray, margin_m: float, dtype) -> tuple[np.ndarray, ...]:
    """The per-box parameters of the in-box test in `dtype` (float32 or float64; anything else
    float64): cos and sin of the heading `(...)`, the centre `(..., 3)` and the half sizes grown
    by `margin_m` `(..., 3)`, for boxes `(..., 7)`. Computed once, they can be repeated or
    broadcast against many points (inside_box_frames)."""
    dtype = dtype if dtype in (np.float32, np.float64) else np.dtype(np.float64)
    boxes = np.asarray(boxes, np.float64)
    cos, sin = np.cos(boxes[..., 6]).astype(dtype), np.sin(boxes[..., 6]).astype(dtype)
    return cos, sin, boxes[..., :3].astype(dtype), (0.5 * boxes[..., 3:6] + margin_m).astype(dtype)


def inside_box_frames(xyz, cos, sin, centre, half) -> np.ndarray:
    """Is each point `xyz (..., 3)` inside its box (parameters of box_frames, broadcast against
    the points' leading shape)? Boundaries included; in the points' dtype."""
    dx = xyz[..., 0] - centre[..., 0]
    dy = xyz[..., 1] - centre[..., 1]
    inside = np.abs(cos * dx + sin * dy) <= half[..., 0]
    inside &= np.abs(cos * dy - sin * dx) <= half[..., 1]
    inside &= np.abs(xyz[..., 2] - centre[..., 2]) <= half[..., 2]
    return inside


def _cell_keys(ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
    return ix.astype(np.int64) * (1 << 32) + iy.astype(np.int64)


def point_box_pairs(
    points: np.ndarray, boxes: np.ndarray, margin_m: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """All (point, box) containments: `(K,)` int64 point indices (ascending) and box indices.

    Within one point the box indices ascend. Candidates come from a coarse BEV grid whose cell is
    at least one box diameter, so each box touches at most 2 x 2 cells; no M x N matrix is built.
    """
    points = np.asarray(points)
    boxes = _as_boxes(boxes)
    if len(points) == 0 or len(boxes) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    xy = np.asarray(points[:, :2], dtype=np.float64)  # (M, 2)
    radius = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4]) + max(margin_m, 0.0)  # (N,)
    cell = max(2.0 * float(radius.max()), 1.0)
    low = np.floor((boxes[:, :2] - radius[:, None]) / cell).astype(np.int64)  # (N, 2)
    high = np.floor((boxes[:, :2] + radius[:, None]) / cell).astype(np.int64)
    # every box covers the cells low..high (at most 2 per axis): enumerate the 4 corners, dedupe
    corner_x = np.stack([low[:, 0], high[:, 0], low[:, 0], high[:, 0]], axis=1)  # (N, 4)
    corner_y = np.stack([low[:, 1], low[:, 1], high[:, 1], high[:, 1]], axis=1)
    box_keys = _cell_keys(corner_x, corner_y).reshape(-1)  # (4N,)
    box_ids = np.repeat(np.arange(len(boxes), dtype=np.int64), 4)
    order = np.lexsort((box_ids, box_keys))
    box_keys, box_ids = box_keys[order], box_ids[order]
    unique = np.r_[True, (box_keys[1:] != box_keys[:-1]) | (box_ids[1:] != box_ids[:-1])]
    box_keys, box_ids = box_keys[unique], box_ids[unique]

    cells = np.floor(xy / cell).astype(np.int64)  # (M, 2)
    point_keys = _cell_keys(cells[:, 0], cells[:, 1])
    start = np.searchsorted(box_keys, point_keys, side="left")
    stop = np.searchsorted(box_keys, point_keys, side="right")
    counts = stop - start  # (M,) candidate boxes per point
    point_index = np.repeat(np.arange(len(points), dtype=np.int64), counts)
    first = np.repeat(start - np.cumsum(counts) + counts, counts)  # start of each run, repeated
    box_index = box_ids[first + np.arange(len(point_index))]
    # the in-box parameters once per box (N), gathered per candidate pair (K >> N)
    cos, sin, centre, half = box_frames(boxes, margin_m, np.float64)
    inside = inside_box_frames(
        np.asarray(points[point_index, :3], dtype=np.float64),
        cos[box_index],
        sin[box_index],
        centre[box_index],
        half[box_index],
    )
    return point_index[inside], box_index[inside]


def point_box_indices(points: np.ndarray, boxes: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
    """Index of the box containing each point `(M,)` int64, -1 if none; the first box wins.

    points `(M, >=3)`, boxes `(N, 7)`; `margin_m` grows every box by that much on each side.
    """
    result = np.full(len(points), -1, dtype=np.int64)
    point_index, box_index = point_box_pairs(points, boxes, margin_m)
    if len(point_index):
        first = np.r_[True, point_index[1:] != point_index[:-1]]  # lowest box index per point
        result[point_index[first]] = box_index[first]
    return result


def count_points_in_boxes(
    points: np.ndarray, boxes: np.ndarray, margin_m: float = 0.0
) -> np.ndarray:
    """Points inside each box `(N,)` int32; a point inside two overlapping boxes counts for both."""
    boxes = _as_boxes(boxes)
    _, box_index = point_box_pairs(points, boxes, margin_m)
    return np.bincount(box_index, minlength=len(boxes)).astype(np.int32)


# ---------------------------------------------------------------------------------------------
# Rotated rectangle intersection (vectorized Sutherland-Hodgman on complex coordinates)
#
# BEV points are complex numbers x + iy. Box a is expressed in box b's frame, where b is the
# axis-aligned rectangle [-l/2, l/2] x [-w/2, w/2]; a is clipped by b's four half-planes. A clip
# step emits, per vertex, the vertex (if inside) and the edge's crossing point (if the edge
# crosses), then packs the emitted points to the front. Crossing parameters divide by a difference
# of opposite-signed sides, so they always lie in [0, 1]: no tolerances are needed.

_CORNER_SIGNS = np.array([1 + 1j, -1 + 1j, -1 - 1j, 1 - 1j])  # CCW, as _BEV_SIGNS


def _clip_half_plane(poly, count, bound, coordinate, sign, capacity):
    """Keep the part of polygons `(P, K)` complex with `sign * coordinate <= bound (P,)`.

    `count (P,)` leading vertices are valid. Returns polygons `(P, capacity)`, their counts and a
    flag `(P,)` for rows that produced more than `capacity` vertices (output truncated).
    """
    rows, slots = poly.shape
    row_index = np.arange(rows)
    values = poly.real if coordinate == 0 else poly.imag
    side = bound[:, None] - sign * values  # (P, K), >= 0: inside
    valid = np.arange(slots)[None, :] < count[:, None]
    last = np.maximum(count - 1, 0)
    # the next vertex, cyclic over the valid ones; zeros (not np.empty) in the slots past a row's
    # last vertex: they are never emitted, but uninitialized memory there made `cut *= t` warn
    # "invalid value" now and then (seen in a dali compare run)
    poly_next = np.zeros_like(poly)
    poly_next[:, :-1] = poly[:, 1:]
    poly_next[row_index, last] = poly[:, 0]
    side_next = np.zeros_like(side)
    side_next[:, :-1] = side[:, 1:]
    side_next[row_index, last] = side[:, 0]
    inside = side >= 0
    keep = valid & inside
    crossing = valid & (inside != (side_next >= 0))
    t = side / np.where(crossing, side - side_next, 1.0)  # (P, K) in [0, 1] where crossing
    cut = poly_next - poly  # the crossing point poly + t (poly_next - poly), in place
    cut *= t
    cut += poly
    # output order per vertex: the vertex (if kept), then its edge's crossing (if any)
    emit = np.empty((rows, slots, 2), dtype=np.int32)
    emit[:, :, 0] = keep
    emit[:, :, 1] = crossing
    position = np.cumsum(emit.reshape(rows, 2 * slots), axis=1).reshape(rows, slots, 2)
    new_count = position[:, -1, -1]
    width = capacity + 1  # one spare slot per row takes every unused or overflowing point
    base = (row_index * width - 1)[:, None]
    spare = (row_index * width + capacity)[:, None]
    target_vertex = np.where(
        keep & (position[:, :, 0] <= capacity), position[:, :, 0] + base, spare
    )
    target_cut = np.where(
        crossing & (position[:, :, 1] <= capacity), position[:, :, 1] + base, spare
    )
    out = np.zeros(rows * width, dtype=np.complex128)
    out[target_vertex.ravel()] = poly.ravel()
    out[target_cut.ravel()] = cut.ravel()
    out = out.reshape(rows, width)[:, :capacity]
    return out, np.minimum(new_count, capacity), new_count > capacity


def _polygon_area(poly: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Shoelace area `(P,)` of complex polygons `(P, K)` with `count` leading valid vertices."""
    rows, slots = poly.shape
    valid = np.arange(slots)[None, :] < count[:, None]
    poly_next = np.zeros_like(poly)  # as in _clip_half_plane: no uninitialized slots
    poly_next[:, :-1] = poly[:, 1:]
    poly_next[np.arange(rows), np.maximum(count - 1, 0)] = poly[:, 0]
    terms = (poly.conj() * poly_next).imag  # cross(p, p_next)
    return 0.5 * np.where(valid, terms, 0.0).sum(axis=1)


def _clip_in_frame(a: np.ndarray, b: np.ndarray, lossless: bool) -> tuple:
    """Area of a ∩ b `(P,)` and an overflow flag `(P,)` for row-wise boxes `(P, 7)`."""
    offset = (a[:, 0] - b[:, 0]) + 1j * (a[:, 1] - b[:, 1])  # small numbers even far away
    center = offset * np.exp(-1j * b[:, 6])  # a's centre in b's frame
    turn = np.exp(1j * (a[:, 6] - b[:, 6]))
    half = _CORNER_SIGNS.real[None] * (a[:, 3:4] / 2) + 1j * _CORNER_SIGNS.imag[None] * (
        a[:, 4:5] / 2
    )
    poly = center[:, None] + turn[:, None] * half  # (P, 4) a's corners in b's frame, CCW
    count = np.full(len(a), 4)
    overflow = np.zeros(len(a), dtype=bool)
    half_l, half_w = b[:, 3] / 2, b[:, 4] / 2
    for bound, coordinate, sign in (
        (half_l, 0, 1),
        (half_l, 0, -1),
        (half_w, 1, 1),
        (half_w, 1, -1),
    ):
        slots = poly.shape[1]
        capacity = 2 * slots if lossless else slots + 1  # a convex polygon gains <= 1 vertex
        poly, count, over = _clip_half_plane(poly, count, bound, coordinate, sign, capacity)
        overflow |= over
    return np.maximum(_polygon_area(poly, count), 0.0), overflow


def bev_intersection_pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """BEV intersection area `(N,)` float64 (m^2) of row-wise box pairs a[i], b[i] `(N, 7)`."""
    a, b = _as_boxes(a), _as_boxes(b)
    if a.shape != b.shape:
        raise ValueError(f"pairwise inputs differ in shape: {a.shape} vs {b.shape}")
    area = np.zeros(len(a))
    for start in range(0, len(a), _PAIR_BLOCK):
        part = slice(start, start + _PAIR_BLOCK)
        block_area, overflow = _clip_in_frame(a[part], b[part], lossless=False)
        if overflow.any():  # rounding made a clipped polygon non-convex: redo without truncation
            block_area[overflow], _ = _clip_in_frame(a[part][overflow], b[part][overflow], True)
        area[part] = block_area
    return np.minimum(area, np.minimum(a[:, 3] * a[:, 4], b[:, 3] * b[:, 4]))


def _height_overlap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    top = np.minimum(a[:, 2] + a[:, 5] / 2, b[:, 2] + b[:, 5] / 2)
    bottom = np.maximum(a[:, 2] - a[:, 5] / 2, b[:, 2] - b[:, 5] / 2)
    return np.clip(top - bottom, 0.0, np.minimum(a[:, 5], b[:, 5]))


def _ratio(intersection: np.ndarray, size_a: np.ndarray, size_b: np.ndarray) -> np.ndarray:
    union = size_a + size_b - intersection
    safe = np.where(union > 0, union, 1.0)
    return np.clip(np.where(union > 0, intersection / safe, 0.0), 0.0, 1.0)


def bev_iou_pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotated BEV IoU `(N,)` float64 of row-wise pairs a[i], b[i] `(N, 7)`; 0 for empty unions."""
    a, b = _as_boxes(a), _as_boxes(b)
    iou = _ratio(bev_intersection_pairs(a, b), a[:, 3] * a[:, 4], b[:, 3] * b[:, 4])
    identical = np.all(a == b, axis=1) & (a[:, 3] * a[:, 4] > 0)
    return np.where(identical, 1.0, iou)


def iou_3d_pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """3D IoU `(N,)` float64 of row-wise pairs: BEV intersection x height overlap over the union."""
    a, b = _as_boxes(a), _as_boxes(b)
    intersection = bev_intersection_pairs(a, b) * _height_overlap(a, b)
    iou = _ratio(intersection, a[:, 3] * a[:, 4] * a[:, 5], b[:, 3] * b[:, 4] * b[:, 5])
    identical = np.all(a == b, axis=1) & (a[:, 3] * a[:, 4] * a[:, 5] > 0)
    return np.where(identical, 1.0, iou)


def overlapping_pairs(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j) whose BEV bounding circles touch: the only pairs that can overlap.

    a `(N, 7)`, b `(M, 7)`; returns two `(K,)` int64 arrays, i ascending. Works in row blocks so
    memory stays bounded for large N x M.
    """
    a, b = _as_boxes(a), _as_boxes(b)
    radius_a = 0.5 * np.hypot(a[:, 3], a[:, 4])
    radius_b = 0.5 * np.hypot(b[:, 3], b[:, 4])
    rows_per_block = max(1, (1 << 22) // max(len(b), 1))
    found_i, found_j = [], []
    for start in range(0, len(a), rows_per_block):
        part = slice(start, start + rows_per_block)
        dx = a[part, None, 0] - b[None, :, 0]  # (n, M)
        dy = a[part, None, 1] - b[None, :, 1]
        reach = radius_a[part, None] + radius_b[None, :]
        # slack so that touching boxes are never rejected by rounding
        i, j = np.nonzero(dx * dx + dy * dy <= (reach * (1 + 1e-9) + 1e-9) ** 2)
        found_i.append(i + start)
        found_j.append(j)
    if not found_i:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(found_i).astype(np.int64), np.concatenate(found_j).astype(np.int64)


def _pairwise(a: np.ndarray, b: np.ndarray, pairs_fn) -> np.ndarray:
    """`(N, M)` float64 of `pairs_fn` over the box pairs of a `(N, 7)` x b `(M, 7)` that can
    overlap (bounding circles touch); 0 elsewhere."""
    a, b = _as_boxes(a), _as_boxes(b)
    result = np.zeros((len(a), len(b)))
    i, j = overlapping_pairs(a, b)
    if len(i):
        result[i, j] = pairs_fn(a[i], b[j])
    return result


def bev_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise rotated BEV IoU `(N, M)` float64 of boxes a `(N, 7)` and b `(M, 7)`."""
    return _pairwise(a, b, bev_iou_pairs)


def iou_3d(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise 3D IoU `(N, M)` float64 of boxes a `(N, 7)` and b `(M, 7)` (yaw about z only)."""
    return _pairwise(a, b, iou_3d_pairs)


def nms_bev(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Greedy BEV non-maximum suppression: kept indices `(K,)` int64 by descending score.

    A box is suppressed when its BEV IoU with a kept, higher-scoring box is > iou_threshold
    (strict, as OpenPCDet's nms_gpu). Ties in score keep the earlier index first.
    """
    boxes = _as_boxes(boxes)
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if len(scores) != len(boxes):
        raise ValueError(f"{len(scores)} scores for {len(boxes)} boxes")
    if len(boxes) == 0:
        return np.zeros(0, np.int64)
    order = np.argsort(-scores, kind="stable")
    ranked = boxes[order]
    i, j = overlapping_pairs(ranked, ranked)
    keep_pair = i < j
    i, j = i[keep_pair], j[keep_pair]
    overlapping = bev_iou_pairs(ranked[i], ranked[j]) > iou_threshold
    i, j = i[overlapping], j[overlapping]  # i ranks above j; i sorted ascending
    starts = np.searchsorted(i, np.arange(len(ranked) + 1))
    suppressed = np.zeros(len(ranked), dtype=bool)
    kept = []
    for rank in range(len(ranked)):  # a loop over boxes, each step vectorized over neighbours
        if suppressed[rank]:
            continue
        kept.append(rank)
        suppressed[j[starts[rank] : starts[rank + 1]]] = True
    return order[np.asarray(kept, dtype=np.int64)]


# ---------------------------------------------------------------------------------------------
# Sensor <-> ground frame, PTSN scaling about the ground


def sensor_to_ground(xyz: np.ndarray, mount_height_m: float) -> np.ndarray:
    """Copy of `(N, >=3)` coordinates with z raised by the mount height (ground near z = 0);
    dtype kept."""
    out = np.array(xyz, copy=True)
    out[..., 2] += mount_height_m
    return out


def ground_to_sensor(xyz: np.ndarray, mount_height_m: float) -> np.ndarray:
    """Inverse of sensor_to_ground: z lowered by the mount height (sensor at the origin)."""
    out = np.array(xyz, copy=True)
    out[..., 2] -= mount_height_m
    return out


# The one PTSN scaling about the ground (the detector's network input, self-training, tests):
# in the ground frame, x, y, z of points and the centres and sizes of boxes are multiplied by s
# (the ground plane stays put, intensity and yaw unchanged); boxes come back divided by s.


def scale_ground_points(points: np.ndarray, s: float) -> np.ndarray:
    """Ground-frame points `(N, >=3)` with x, y, z multiplied by `s`; dtype kept (float32 points
    are scaled in float32), other columns copied untouched."""
    out = np.array(points, copy=True)
    out[:, :3] *= s
    return out


def scale_ground_boxes(boxes: np.ndarray, s: float) -> np.ndarray:
    """Ground-frame boxes `(N, 7)` float64 with centres and l, w, h multiplied by `s`, yaw kept."""
    out = np.array(boxes, np.float64, copy=True).reshape(-1, 7)
    out[:, :6] *= s
    return out


def unscale_ground_boxes(boxes: np.ndarray, s: float) -> np.ndarray:
    """Undo scale_ground_boxes: centres and l, w, h divided by `s` `(N, 7)` float64."""
    out = np.array(boxes, np.float64, copy=True).reshape(-1, 7)
    out[:, :6] /= s
    return out


def scale_points_about_ground(points: np.ndarray, s: float, mount_height_m: float) -> np.ndarray:
    """Sensor-frame points `(N, >=3)` as PTSN sees them, back in the sensor frame: scaled by `s`
    about the ground point below the sensor; dtype kept."""
    ground = scale_ground_points(sensor_to_ground(points, mount_height_m), s)
    return ground_to_sensor(ground, mount_height_m)


def scale_boxes_about_ground(boxes: np.ndarray, s: float, mount_height_m: float) -> np.ndarray:
    """Sensor-frame boxes `(N, 7)` scaled by `s` about the ground point below the sensor."""
    ground = scale_ground_boxes(sensor_to_ground(_as_boxes(boxes), mount_height_m), s)
    return ground_to_sensor(ground, mount_height_m)


def descale_boxes_about_ground(boxes: np.ndarray, s: float, mount_height_m: float) -> np.ndarray:
    """Undo scale_boxes_about_ground (what Detector.predict does to the network's boxes)."""
    ground = unscale_ground_boxes(sensor_to_ground(_as_boxes(boxes), mount_height_m), s)
    return ground_to_sensor(ground, mount_height_m)


def iou_pairs_bev_3d(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both BEV and 3D IoU `(N,)` of row-wise pairs, sharing one polygon clipping."""
    a, b = _as_boxes(a), _as_boxes(b)
    intersection = bev_intersection_pairs(a, b)
    bev = _ratio(intersection, a[:, 3] * a[:, 4], b[:, 3] * b[:, 4])
    volume = _ratio(
        intersection * _height_overlap(a, b),
        a[:, 3] * a[:, 4] * a[:, 5],
        b[:, 3] * b[:, 4] * b[:, 5],
    )
    identical = np.all(a == b, axis=1)
    bev = np.where(identical & (a[:, 3] * a[:, 4] > 0), 1.0, bev)
    volume = np.where(identical & (a[:, 3] * a[:, 4] * a[:, 5] > 0), 1.0, volume)
    return bev, volume
