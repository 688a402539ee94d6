"""Point models of the model library: labelled source instances with enough points, in
box-normalized coordinates (x/l, y/w, z/h in the box frame, in [-0.5, 0.5]^3) with their
viewing angle."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dali_cli.geometry import point_box_indices, points_in_box_frames, wrap_angle
from dali_cli.store.artifacts import (
    FrameSet,
    read_boxes,
)


@dataclass
class PointModels:
    """Point models of labelled instances, stored column-wise.

    points: `(P, 4)` float32 x, y, z in box-normalized coordinates ([-0.5, 0.5] in the box frame:
    x along l, y along w, z up) and intensity; offsets: `(K + 1,)` int64, model k is
    points[offsets[k]:offsets[k+1]]. view_angle_rad: `(K,)` azimuth of the sensor as seen from
    the box, in the box frame (atan2 of the box-frame sensor position), in [-pi, pi).
    lwh: `(K, 3)` the instance's box size; yaw, range_m: `(K,)`; model_id, frame_id, sensor:
    `(K,)` str.
    """

    points: np.ndarray
    offsets: np.ndarray
    view_angle_rad: np.ndarray
    lwh: np.ndarray
    yaw: np.ndarray
    range_m: np.ndarray
    model_id: np.ndarray
    frame_id: np.ndarray
    sensor: np.ndarray

    def __len__(self) -> int:
        return len(self.offsets) - 1

    @property
    def num_points(self) -> np.ndarray:
        return np.diff(self.offsets).astype(np.int32)

    def model_points(self, index: int) -> np.ndarray:
        """`(M, 4)` float32 normalized points (+ intensity) of model `index`."""
        return self.points[self.offsets[index] : self.offsets[index + 1]]

    @classmethod
    def empty(cls) -> PointModels:
        return cls(
            points=np.zeros((0, 4), np.float32),
            offsets=np.zeros(1, np.int64),
            view_angle_rad=np.zeros(0),
            lwh=np.zeros((0, 3)),
            yaw=np.zeros(0),
            range_m=np.zeros(0),
            model_id=np.zeros(0, dtype=object),
            frame_id=np.zeros(0, dtype=object),
            sensor=np.zeros(0, dtype=object),
        )

    @staticmethod
    def concat(parts: Sequence[PointModels]) -> PointModels:
        parts = [p for p in parts if len(p)]
        if not parts:
            return PointModels.empty()
        sizes = np.concatenate([np.diff(p.offsets) for p in parts])
        return PointModels(
            points=np.concatenate([p.points for p in parts]).astype(np.float32),
            offsets=np.r_[0, np.cumsum(sizes)].astype(np.int64),
            **{
                name: np.concatenate([getattr(p, name) for p in parts])
                for name in (
                    "view_angle_rad",
                    "lwh",
                    "yaw",
                    "range_m",
                    "model_id",
                    "frame_id",
                    "sensor",
                )
            },
        )


def point_models_from_frame(
    points: np.ndarray,
    boxes: np.ndarray,
    frame_id: str,
    sensor: str = "",
    min_points: int = 300,
    origin: np.ndarray | None = None,
) -> PointModels:
    """Point models of one labelled frame: boxes `(N, 7)` holding >= `min_points` of `points` `(n, 4)`.

    Coordinates are box-normalized (local / (l, w, h)); the viewing angle is the azimuth of the
    sensor `origin` (default 0) seen from the box, in the box frame.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    points = np.asarray(points, np.float32)
    if len(boxes) == 0 or len(points) == 0:
        return PointModels.empty()
    owner = point_box_indices(points, boxes)
    counts = np.bincount(owner[owner >= 0], minlength=len(boxes))
    keep = np.flatnonzero(counts >= int(min_points))
    if len(keep) == 0:
        return PointModels.empty()
    selected = np.flatnonzero(np.isin(owner, keep))
    selected = selected[np.argsort(owner[selected], kind="stable")]  # grouped by box, kept order
    box_of_point = boxes[owner[selected]]  # (P, 7)
    local = points_in_box_frames(points[selected, :3], box_of_point) / box_of_point[:, 3:6]
    normalized = np.concatenate([local, points[selected, 3:4]], axis=1).astype(np.float32)
    origin = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
    kept = boxes[keep]
    sensor_local = points_in_box_frames(np.broadcast_to(origin, (len(kept), 3)), kept)
    return PointModels(
        points=normalized,
        offsets=np.r_[0, np.cumsum(counts[keep])].astype(np.int64),
        view_angle_rad=wrap_angle(np.arctan2(sensor_local[:, 1], sensor_local[:, 0])),
        lwh=kept[:, 3:6].copy(),
        yaw=kept[:, 6].copy(),
        range_m=np.linalg.norm(kept[:, :2] - origin[:2], axis=1),
        model_id=np.array([f"{frame_id}#{k}" for k in keep], dtype=object),
        frame_id=np.full(len(keep), str(frame_id), dtype=object),
        sensor=np.full(len(keep), str(sensor), dtype=object),
    )


def point_models_from_frameset(
    data_dir: str | Path, min_points: int = 300, label: str | None = "Car", progress: bool = True
) -> PointModels:
    """Point models of every labelled instance of a FrameSet + boxes.parquet directory."""
    from tqdm import tqdm

    frames = FrameSet(data_dir)
    table = read_boxes(data_dir)
    if label is not None and len(table):
        table = table.select(np.asarray(table["label"]).astype(str) == label)
    by_frame = table.rows_by_frame()
    indices = [i for i, fid in enumerate(frames.frame_ids) if fid in by_frame]
    parts = []
    for frame_id, points in tqdm(
        frames.iter_frames(indices), total=len(indices), desc="point models", disable=not progress
    ):
        rows = by_frame[frame_id]
        parts.append(
            point_models_from_frame(points, table.boxes[rows], frame_id, frames.sensor, min_points)
        )
    return PointModels.concat(parts)
