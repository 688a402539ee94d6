"""How far a car's surface sits inside its labelled box: per car, the median depth of the points on
the end face and on the side face that face the sensor. Real KITTI cars' ends bulge and their
boxes hold them with room to spare, so their end-face points lie about 0.14 m inside the box;
a detector trained on cars whose surface fills the box places real boxes too far away. Pure
functions over arrays (sensor frame, metres)."""

from __future__ import annotations

import numpy as np

from dali_cli.geometry import point_box_pairs

MIN_POINTS = 40  # fewer points on the car: no inset (a far car's face is a handful of returns)
FACE_DEPTH_M = 0.3  # points this close to a face (inside or out) belong to it
GROWN_M = 0.4  # the box grown by this much on each side gathers the car's points
GROUND_CLEARANCE_M = 0.25  # points this close to the box bottom are ground or wheels: left out
TOP_M = 0.2  # points higher than this above the box are not the car's
FACE_VIEW_M = 1.0  # a face counts when the sensor lies at least this far in front of its plane
END_MARGIN_M = 0.35  # the end face's points lie this far from the sides (its corners are round)
SIDE_MARGIN_M = 0.6  # the side face's points lie this far from the ends
MIN_FACE_POINTS = 5


def _face_inset(depth: np.ndarray, half: float, on_face: np.ndarray) -> float:
    """Median depth below the face at `half` of the points `on_face`; NaN for too few."""
    if on_face.sum() < MIN_FACE_POINTS:
        return float("nan")
    return float(half - np.median(depth[on_face]))


def surface_insets(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """`(K, 2)` float64: per box `(K, 7)` the end-face and side-face inset (m, > 0 inside the box).

    points: `(N, 3+)` x, y, z in the sensor frame. For each box, its points (the box grown by
    GROWN_M, without the lowest GROUND_CLEARANCE_M and more than TOP_M above it) in the box
    frame; the end face (and side face) turned to the sensor, seen when the sensor lies
    FACE_VIEW_M beyond its plane; the face's points are those within FACE_DEPTH_M of it, away
    from the corners. NaN where the car has fewer than MIN_POINTS points or the face is not seen.
    """
    xyz = np.asarray(points, np.float64)
    xyz = xyz[:, :3] if xyz.ndim == 2 else xyz.reshape(-1, 3)
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    insets = np.full((len(boxes), 2), np.nan)
    # each box's candidate points once, from the shared grid lookup (no pass over the frame per box)
    point_index, box_index = point_box_pairs(xyz, boxes, GROWN_M)
    order = np.argsort(box_index, kind="stable")
    point_index, box_index = point_index[order], box_index[order]
    bounds = np.searchsorted(box_index, np.arange(len(boxes) + 1))
    for k, (x, y, z, length, width, height, yaw) in enumerate(boxes):
        own = xyz[point_index[bounds[k] : bounds[k + 1]]]
        cos, sin = np.cos(yaw), np.sin(yaw)
        dx, dy = own[:, 0] - x, own[:, 1] - y
        along, across, up = cos * dx + sin * dy, -sin * dx + cos * dy, own[:, 2] - z
        half_l, half_w, half_h = length / 2, width / 2, height / 2
        near = (up > -half_h + GROUND_CLEARANCE_M) & (up < half_h + TOP_M)
        if near.sum() < MIN_POINTS:
            continue
        along, across = along[near], across[near]
        sensor_along, sensor_across = -(cos * x + sin * y), -(-sin * x + cos * y)
        if abs(sensor_along) > half_l + FACE_VIEW_M:
            depth = np.sign(sensor_along) * along
            face = (depth > half_l - FACE_DEPTH_M) & (np.abs(across) < half_w - END_MARGIN_M)
            insets[k, 0] = _face_inset(depth, half_l, face)
        if abs(sensor_across) > half_w + FACE_VIEW_M:
            depth = np.sign(sensor_across) * across
            face = (depth > half_w - FACE_DEPTH_M) & (np.abs(along) < half_l - SIDE_MARGIN_M)
            insets[k, 1] = _face_inset(depth, half_w, face)
    return insets
