"""Training data: labeled frame sets held in memory (ground frame), and the augmentation
pipeline that turns a few of their frames into one training batch."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from dali_cli.detector import augment
from dali_cli.detector.config import DetectorConfig
from dali_cli.store.artifacts import ArtifactError, FrameSet, read_boxes


@dataclass
class Augmentation:
    """Which augmentations run, with their ranges. `object_scale` is ROS (None = off)."""

    gt_sampling: bool = True
    gt_sample_count: int = 45  # paste cars until a frame has about this many (see docs: Ablations)
    flip: bool = True
    rotation_rad: float = np.pi / 8  # global rotation U(-r, r); pi/4: -1.6 / -8.0 AP_3D (2 seeds)
    scaling: tuple[float, float] = (0.95, 1.05)  # global scaling about the ground
    object_noise: bool = True
    object_scale: tuple[float, float] | None = None  # ROS: U(lo, hi) per object, l, w, h alike

    @classmethod
    def none(cls) -> Augmentation:
        return cls(False, 0, False, 0.0, (1.0, 1.0), False, None)


@dataclass
class LabeledFrames:
    """A labeled training set in memory. points[i]: (n_i, 4) float32 and boxes[i]: (m_i, 7)
    float64, both in the ground frame (sensor z + mount_height_m)."""

    name: str
    sensor: str
    mount_height_m: float
    frame_ids: list[str]
    points: list[np.ndarray]
    boxes: list[np.ndarray]
    database: augment.ObjectDatabase | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def num_boxes(self) -> int:
        return int(sum(len(b) for b in self.boxes))

    def mean_lwh(self) -> np.ndarray:
        """Mean l, w, h (3,) of all boxes."""
        boxes = np.concatenate(self.boxes) if self.boxes else np.zeros((0, 7))
        return boxes[:, 3:6].mean(axis=0) if len(boxes) else np.full(3, np.nan)


def load_labeled(
    data_dir: str | Path,
    config: DetectorConfig,
    boxes_dir: str | Path | None = None,
    labels: tuple[str, ...] = ("Car",),
    min_points: int = 1,
    sensors_path: str | Path | None = None,
) -> LabeledFrames:
    """Read a FrameSet and its boxes.parquet (same directory unless `boxes_dir`) into memory.

    Points and boxes that global rotation (<= 45 deg) cannot bring into the detection range are
    dropped (beyond its far corner + 10 m, or more than 135 deg off +x for a front range); boxes
    of other labels or with fewer than `min_points` points are not targets. A box of `labels`
    outside dali_cli.labels.plausibility's limits (size, distance from the sensor) is an ArtifactError
    naming the file, row, frame and field: corrupt labels or labels not in metres.
    """
    from dali_cli.geometry import count_points_in_boxes
    from dali_cli.labels import plausibility
    from dali_cli.sensors import get_profile

    frames = FrameSet(data_dir)
    table = read_boxes(boxes_dir or data_dir)
    if not frames.sensor:
        raise ArtifactError(f"{frames.path}: attrs has no 'sensor' (needed for the mount height)")
    profile = get_profile(frames.sensor, sensors_path)
    mount = profile.mount_height_m
    known = set(frames.frame_ids)
    unknown = sorted(set(table.frame_id.astype(str)) - known)
    if unknown:
        raise ArtifactError(
            f"{Path(boxes_dir or data_dir) / 'boxes.parquet'}: frame_id '{unknown[0]}' is not in {frames.path}"
        )
    targets = np.isin(table["label"].astype(str), labels)
    plausibility.refuse_implausible(
        table.boxes,
        targets,
        str(Path(boxes_dir or data_dir) / "boxes.parquet"),
        table.frame_id,
        profile.max_range_m,
    )
    table = table.select(targets)
    rows = table.rows_by_frame()
    far = (
        np.hypot(max(abs(v) for v in config.x_range_m), max(abs(v) for v in config.y_range_m)) + 10
    )
    reach = np.radians(135.0) if config.x_range_m[0] >= 0 else np.pi + 1e-9
    all_points, all_boxes = [], []
    for frame_id, points in frames.iter_frames():
        # only what global rotation (<= 45 deg) can bring into the range: radius and azimuth
        keep = (np.hypot(points[:, 0], points[:, 1]) < far) & (
            np.abs(np.arctan2(points[:, 1], points[:, 0])) < reach
        )
        points = points[keep].copy()
        points[:, 2] += mount
        boxes = table.select(rows.get(frame_id, np.zeros(0, np.int64))).boxes
        boxes[:, 2] += mount
        if len(boxes):
            visible = np.abs(np.arctan2(boxes[:, 1], boxes[:, 0])) < reach
            boxes = boxes[visible & (count_points_in_boxes(points, boxes) >= min_points)]
        all_points.append(points)
        all_boxes.append(boxes)
    return LabeledFrames(
        str(data_dir), frames.sensor, mount, list(frames.frame_ids), all_points, all_boxes
    )


def size_normalize(frames: LabeledFrames, delta_lwh: np.ndarray) -> LabeledFrames:
    """SN (Wang et al. 2020): every box's l, w, h += delta_lwh, its points scaled with it."""
    from dali_cli.size_norm import shift_frame

    delta_lwh = np.asarray(delta_lwh, np.float64).reshape(3)
    points, boxes = [], []
    for frame_points, frame_boxes in zip(frames.points, frames.boxes, strict=True):
        new_points, new_boxes = shift_frame(frame_points, frame_boxes, delta_lwh)
        points.append(new_points)
        boxes.append(new_boxes)
    return LabeledFrames(
        frames.name, frames.sensor, frames.mount_height_m, frames.frame_ids, points, boxes
    )


def scale_about_ground(frames: LabeledFrames, scale: float) -> LabeledFrames:
    """PTSN's view of a labeled set: points (x, y, z) and boxes (centres and l, w, h) multiplied
    by `scale` in the ground frame (the ground plane stays put; intensity and yaw unchanged).
    This is the cloud `Detector.predict(..., scale=scale)` feeds the network."""
    from dali_cli.geometry import scale_ground_boxes, scale_ground_points

    points = [scale_ground_points(p, scale) for p in frames.points]  # (n, 4): intensity kept
    boxes = [scale_ground_boxes(b, scale) for b in frames.boxes]  # (m, 7): yaw kept
    return LabeledFrames(
        frames.name, frames.sensor, frames.mount_height_m, frames.frame_ids, points, boxes
    )


def detection_region(config: DetectorConfig) -> tuple[float, float, float, float]:
    return (*config.x_range_m, *config.y_range_m)


class Sample(NamedTuple):
    """One augmented training frame, ground frame: points (n, 4) float32, boxes (m, 7) float64
    (the targets)."""

    points: np.ndarray
    boxes: np.ndarray


def augmented_sample(
    frames: LabeledFrames, index: int, rng: np.random.Generator, settings: Augmentation
) -> Sample:
    """One augmented frame: ground-truth sampling, object scaling and noise, then the frame's
    flip, rotation and scaling, each drawn from `rng` in that order."""
    points, boxes = frames.points[index], frames.boxes[index]
    if settings.gt_sampling and frames.database is not None:
        points, boxes = augment.sample_ground_truth(
            points, boxes, frames.database, rng, settings.gt_sample_count
        )
    if settings.object_scale is not None and len(boxes):
        factor = rng.uniform(*settings.object_scale, size=len(boxes))
        points, boxes = augment.scale_objects(points, boxes, np.repeat(factor[:, None], 3, axis=1))
    if settings.object_noise:
        points, boxes = augment.object_noise(points, boxes, rng)
    if settings.flip and rng.random() < 0.5:
        points, boxes = augment.flip_y(points, boxes)
    if settings.rotation_rad > 0:
        points, boxes = augment.rotate_scene(
            points, boxes, rng.uniform(-settings.rotation_rad, settings.rotation_rad)
        )
    if settings.scaling != (1.0, 1.0):
        points, boxes = augment.scale_scene(points, boxes, rng.uniform(*settings.scaling))
    return Sample(points, boxes)
