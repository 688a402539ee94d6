"""Data augmentation and size normalization on (points, boxes) of one frame, pure numpy.

points: (n, 4) float32 x, y, z, intensity; boxes: (m, 7) float64; both in the **ground frame**
(z = 0 on the ground), so scalings about the origin keep the ground plane in place. Every function
returns new arrays and draws randomness only from the `rng` it is given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dali_cli.geometry import bev_iou, point_box_indices, wrap_angle


def rotate_z(xyz: np.ndarray, angle: np.ndarray | float) -> np.ndarray:
    """Rotate (n, 3) points about the z axis by `angle` (scalar or (n,)) radians, counter-clockwise."""
    cos, sin = np.cos(angle), np.sin(angle)
    x, y = xyz[:, 0], xyz[:, 1]
    return np.stack([cos * x - sin * y, sin * x + cos * y, xyz[:, 2]], axis=1)


def flip_y(points: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mirror about the x-z plane: y -> -y, yaw -> -yaw."""
    points, boxes = points.copy(), boxes.copy()
    points[:, 1] *= -1
    boxes[:, 1] *= -1
    boxes[:, 6] = wrap_angle(-boxes[:, 6])
    return points, boxes


def rotate_scene(
    points: np.ndarray, boxes: np.ndarray, angle: float
) -> tuple[np.ndarray, np.ndarray]:
    """Rotate the whole frame about the vertical axis through the sensor."""
    points, boxes = points.copy(), boxes.copy()
    points[:, :3] = rotate_z(points[:, :3].astype(np.float64), angle)
    boxes[:, :3] = rotate_z(boxes[:, :3], angle)
    boxes[:, 6] = wrap_angle(boxes[:, 6] + angle)
    return points, boxes


def scale_scene(
    points: np.ndarray, boxes: np.ndarray, factor: float
) -> tuple[np.ndarray, np.ndarray]:
    """Scale the whole frame about the ground point below the sensor (PTSN's scaling)."""
    points, boxes = points.copy(), boxes.copy()
    points[:, :3] *= factor
    boxes[:, :6] *= factor
    return points, boxes


def scale_objects(
    points: np.ndarray, boxes: np.ndarray, factors: np.ndarray, margin_m: float = 0.05
) -> tuple[np.ndarray, np.ndarray]:
    """Resize each box by `factors` (m, 3) along its l, w, h, moving its points with it.

    Scaling is about the box's bottom center in the box frame, so a car stays on the ground. Points
    inside the box (plus `margin_m`) are scaled with it; all other points are untouched. Used by SN
    (factors = target size / source size) and ROS (one random factor per object).
    """
    points, boxes = points.copy(), boxes.copy()
    factors = np.asarray(factors, np.float64).reshape(-1, 3)
    if len(boxes) == 0:
        return points, boxes
    owner = point_box_indices(points, boxes, margin_m=margin_m)  # (n,)
    inside = owner >= 0
    box = boxes[owner[inside]]  # (k, 7)
    bottom = box[:, :3].copy()  # (k, 3) bottom center of each point's box
    bottom[:, 2] -= box[:, 5] / 2
    local = rotate_z(points[inside, :3].astype(np.float64) - bottom, -box[:, 6])  # (k, 3)
    local *= factors[owner[inside]]
    points[inside, :3] = rotate_z(local, box[:, 6]) + bottom
    bottom_z = boxes[:, 2] - boxes[:, 5] / 2
    boxes[:, 3:6] *= factors
    boxes[:, 2] = bottom_z + boxes[:, 5] / 2
    return points, boxes


def object_noise(
    points: np.ndarray,
    boxes: np.ndarray,
    rng: np.random.Generator,
    translation_std_m: tuple[float, float, float] = (0.25, 0.25, 0.1),
    rotation_max_rad: float = np.pi / 20,
) -> tuple[np.ndarray, np.ndarray]:
    """Move and turn each box and its points by a small random amount; moves that would make two
    boxes overlap in BEV are undone."""
    m = len(boxes)
    if m == 0:
        return points.copy(), boxes.copy()
    shift = rng.normal(0.0, translation_std_m, size=(m, 3))  # (m, 3)
    turn = rng.uniform(-rotation_max_rad, rotation_max_rad, size=m)  # (m,)
    moved = boxes.copy()
    moved[:, :3] += shift
    moved[:, 6] = wrap_angle(moved[:, 6] + turn)
    overlap = bev_iou(moved, moved) > 0  # (m, m)
    np.fill_diagonal(overlap, False)
    collides = overlap.any(axis=1)
    shift[collides], turn[collides] = 0.0, 0.0
    moved[collides] = boxes[collides]
    points = points.copy()
    owner = point_box_indices(points, boxes)  # (n,)
    inside = owner >= 0
    center = boxes[owner[inside], :3]  # (k, 3)
    local = points[inside, :3].astype(np.float64) - center
    points[inside, :3] = rotate_z(local, turn[owner[inside]]) + center + shift[owner[inside]]
    return points, moved


@dataclass
class ObjectDatabase:
    """Labelled instances for ground-truth sampling: boxes (k, 7) ground frame and their points,
    concatenated (p, 4) with offsets (k + 1,)."""

    boxes: np.ndarray
    points: np.ndarray
    offsets: np.ndarray
    region: tuple[float, float, float, float] | None = None  # x0, x1, y0, y1 of the boxes kept

    def __len__(self) -> int:
        return len(self.boxes)

    @classmethod
    def build(
        cls,
        frames: list[np.ndarray],
        boxes: list[np.ndarray],
        min_points: int = 5,
        region: tuple[float, float, float, float] | None = None,
    ) -> ObjectDatabase:
        """Collect every box with >= min_points points (and its center in `region`, the detection
        range x0, x1, y0, y1, if given: pasting a car nobody sees is wasted work)."""
        kept_boxes, kept_points = [], []
        for points, frame_boxes in zip(frames, boxes, strict=True):  # frames, not points
            instances = frame_instances(points, frame_boxes, min_points, region)
            kept_boxes.extend(instances[0])
            kept_points.extend(instances[1])
        sizes = [len(p) for p in kept_points]
        return cls(
            boxes=np.asarray(kept_boxes, np.float64).reshape(-1, 7),
            points=np.concatenate(kept_points) if kept_points else np.zeros((0, 4), np.float32),
            offsets=np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
            region=region,
        )


def frame_instances(
    points: np.ndarray,
    boxes: np.ndarray,
    min_points: int = 5,
    region: tuple[float, float, float, float] | None = None,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """One frame's database instances: its boxes (7,) with >= min_points of `points` (n, 4) inside
    (and their centres in `region`), and those points (k_i, 4) each, in box order."""
    if region is not None:
        boxes = boxes[in_region(boxes, region)]
    if len(boxes) == 0:
        return [], []
    owner = point_box_indices(points, boxes)  # (n,)
    order = np.argsort(owner, kind="stable")
    counts = np.bincount(owner[owner >= 0], minlength=len(boxes))
    starts = np.searchsorted(owner[order], np.arange(len(boxes)))
    kept = np.flatnonzero(counts >= min_points)
    return [boxes[j] for j in kept], [
        points[order[starts[j] : starts[j] + counts[j]]] for j in kept
    ]


def in_region(boxes: np.ndarray, region: tuple[float, float, float, float]) -> np.ndarray:
    """(m,) bool: box centers inside x0 <= x < x1, y0 <= y < y1."""
    x0, x1, y0, y1 = region
    return (boxes[:, 0] >= x0) & (boxes[:, 0] < x1) & (boxes[:, 1] >= y0) & (boxes[:, 1] < y1)


def sample_ground_truth(
    points: np.ndarray,
    boxes: np.ndarray,
    database: ObjectDatabase,
    rng: np.random.Generator,
    target_count: int = 15,
) -> tuple[np.ndarray, np.ndarray]:
    """Paste database instances (at their recorded positions) until the frame has about
    `target_count` boxes (in the database's region, if it has one); candidates overlapping any
    box in BEV are dropped, and scene points inside a pasted box are removed (the pasted car
    replaces whatever was there)."""
    present = (
        len(boxes) if database.region is None else int(in_region(boxes, database.region).sum())
    )
    wanted = target_count - present
    if wanted <= 0 or len(database) == 0:
        return points, boxes
    candidates = rng.choice(len(database), size=min(wanted, len(database)), replace=False)
    candidate_boxes = database.boxes[candidates]  # (c, 7)
    accepted = np.zeros(len(candidates), bool)
    existing_overlap = (
        (bev_iou(candidate_boxes, boxes) > 0).any(axis=1)
        if len(boxes)
        else np.zeros(len(candidates), bool)
    )
    mutual = bev_iou(candidate_boxes, candidate_boxes) > 0  # (c, c)
    for i in range(len(candidates)):  # candidates: at most target_count
        accepted[i] = not existing_overlap[i] and not (mutual[i, :i] & accepted[:i]).any()
    if not accepted.any():
        return points, boxes
    chosen = candidates[accepted]
    new_boxes = database.boxes[chosen]
    covered = point_box_indices(points, new_boxes, margin_m=0.1) >= 0
    pasted = [database.points[database.offsets[j] : database.offsets[j + 1]] for j in chosen]
    return (
        np.concatenate([points[~covered], *pasted]).astype(np.float32),
        np.concatenate([boxes, new_boxes]),
    )
