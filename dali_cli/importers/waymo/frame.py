"""One Waymo frame as both formats decode it, and its conversion to dali's conventions.

dali keeps points and boxes in the TOP LiDAR's frame (x forward, y left, z up, origin at the
sensor), like every other importer's sensor frame: Waymo's vehicle-frame points and boxes are
moved by the inverse of the TOP extrinsic.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dali_cli.geometry import wrap_angle
from dali_cli.importers.waymo.range_image import (
    intensity_to_unit,
    range_image_to_points,
    row_inclinations,
)

TOP = 1
LASER_NAMES = {1: "TOP", 2: "FRONT", 3: "SIDE_LEFT", 4: "SIDE_RIGHT", 5: "REAR"}
# Waymo box types → dali labels (Car is what dali trains on)
BOX_LABELS = {0: "DontCare", 1: "Car", 2: "Pedestrian", 3: "Sign", 4: "Cyclist"}


class WaymoFormatError(ValueError):
    """Malformed Waymo data; the message names segment, timestamp and laser where known."""


@dataclass
class LaserCalibration:
    """extrinsic (4, 4) LiDAR → vehicle; inclinations (H,) radians lowest first, or min/max."""

    name: int
    extrinsic: np.ndarray
    inclinations: np.ndarray | None
    inclination_min: float
    inclination_max: float


@dataclass
class LaserScan:
    """One laser's range images (H, W, C) float32 (None when absent) and TOP's pixel pose."""

    name: int
    returns: list[np.ndarray | None]
    pixel_pose: np.ndarray | None = None


@dataclass
class WaymoFrame:
    segment: str
    timestamp_micros: int
    vehicle_pose: np.ndarray | None  # (4, 4) vehicle → world
    calibrations: dict[int, LaserCalibration]
    scans: list[LaserScan]
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))  # vehicle frame
    types: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    num_points: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def where(self, laser: int | None = None) -> str:
        laser_text = f", laser {LASER_NAMES.get(laser, laser)}" if laser is not None else ""
        return f"segment {self.segment}, timestamp {self.timestamp_micros}{laser_text}"


def frame_id(segment: str, timestamp_micros: int) -> str:
    """dali frame id of a Waymo frame: '<segment>_<timestamp_micros>'."""
    return (
        f"{segment.removeprefix('segment-').removesuffix('_with_camera_labels')}_{timestamp_micros}"
    )


def scan_points(
    frame: WaymoFrame, returns: int = 1, lidars: str = "top"
) -> tuple[np.ndarray, dict[int, int]]:
    """All points of the chosen lasers and returns in the vehicle frame: (n, 4) float64 x, y, z,
    intensity in [0, 1), and the point count per laser."""
    chunks, counts = [], {}
    for scan in frame.scans:
        if lidars == "top" and scan.name != TOP:
            continue
        calibration = frame.calibrations.get(scan.name)
        if calibration is None:
            raise WaymoFormatError(f"{frame.where(scan.name)}: no calibration for this laser")
        counts[scan.name] = 0
        for index, image in enumerate(scan.returns[:returns]):
            if image is None:
                continue
            if image.ndim != 3 or image.shape[2] < 2:
                raise WaymoFormatError(
                    f"{frame.where(scan.name)}: return {index + 1} range image has shape "
                    f"{image.shape}, expected (H, W, >=2)"
                )
            try:
                rows = row_inclinations(
                    image.shape[0],
                    calibration.inclinations,
                    calibration.inclination_min,
                    calibration.inclination_max,
                )
            except ValueError as error:
                raise WaymoFormatError(f"{frame.where(scan.name)}: {error}") from None
            use_pose = scan.pixel_pose is not None and frame.vehicle_pose is not None
            points, intensity = range_image_to_points(
                image,
                calibration.extrinsic,
                rows,
                scan.pixel_pose if use_pose else None,
                frame.vehicle_pose if use_pose else None,
            )
            chunks.append(np.column_stack([points, intensity_to_unit(intensity)]))
            counts[scan.name] += len(points)
    if lidars == "top" and TOP not in counts:
        raise WaymoFormatError(f"{frame.where(TOP)}: the TOP LiDAR's range image is missing")
    points = np.concatenate(chunks) if chunks else np.zeros((0, 4))
    return points, counts


def to_top_frame(frame: WaymoFrame, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vehicle-frame points (n, 4) and the frame's boxes → the TOP LiDAR frame:
    (points (n, 4) float32, boxes (N, 7) float64 with heading in [-pi, pi))."""
    top = frame.calibrations.get(TOP)
    if top is None:
        raise WaymoFormatError(f"{frame.where(TOP)}: no TOP calibration (dali's sensor frame)")
    rotation, translation = top.extrinsic[:3, :3], top.extrinsic[:3, 3]
    xyz = (points[:, :3] - translation) @ rotation  # R^T (p - t), row vectors
    out = np.column_stack([xyz, points[:, 3]]).astype(np.float32)
    boxes = np.asarray(frame.boxes, np.float64).reshape(-1, 7).copy()
    if len(boxes):
        boxes[:, :3] = (boxes[:, :3] - translation) @ rotation
        heading = np.stack([np.cos(boxes[:, 6]), np.sin(boxes[:, 6]), np.zeros(len(boxes))], 1)
        turned = heading @ rotation
        boxes[:, 6] = wrap_angle(np.arctan2(turned[:, 1], turned[:, 0]))
    return out, boxes
