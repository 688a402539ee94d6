"""Waymo range images → points, in numpy (the conventions of waymo_open_dataset's
utils/range_image_utils.py and v2/perception/utils/lidar_utils.py, without TensorFlow).

A range image is `(H, W, C)` float32: channel 0 range (m, <= 0 for no return), channel 1
intensity, channel 2 elongation. Row r has the beam inclination `inclinations[H - 1 - r]` (the
calibration lists inclinations from the lowest beam up; row 0 is the highest beam). Column c has
the azimuth `((W - c - 0.5) / W * 2 - 1) * pi - yaw_correction`, yaw_correction being the yaw of
the LiDAR's extrinsic, so that after the extrinsic rotation column W/2 looks along the vehicle's
+x. A point in the LiDAR frame is range * (cos az cos inc, sin az cos inc, sin inc); the extrinsic
(LiDAR → vehicle, 4x4) brings it to the vehicle frame. The TOP LiDAR's per-pixel pose (rolling
shutter: `(H, W, 6)` roll, pitch, yaw, x, y, z = vehicle → world at the pixel's capture time)
together with the frame's vehicle pose undoes the car's motion during the sweep.
"""

from __future__ import annotations

import numpy as np


def uniform_inclinations(minimum: float, maximum: float, height: int) -> np.ndarray:
    """(height,) inclinations in radians, lowest first, at the centres of `height` equal bins
    between `minimum` and `maximum` (Waymo's compute_inclination)."""
    return minimum + (np.arange(height) + 0.5) / height * (maximum - minimum)


def row_inclinations(
    height: int, values: np.ndarray | None, minimum: float, maximum: float
) -> np.ndarray:
    """(height,) inclination of each range-image row (row 0 = highest beam), radians."""
    if values is not None and len(values):
        values = np.asarray(values, np.float64)
        if len(values) != height:
            raise ValueError(f"{len(values)} beam inclinations for a range image of {height} rows")
    else:
        values = uniform_inclinations(minimum, maximum, height)
    return values[::-1]


def column_azimuths(width: int, extrinsic: np.ndarray) -> np.ndarray:
    """(width,) azimuth of each range-image column in the LiDAR frame, radians."""
    yaw_correction = np.arctan2(extrinsic[1, 0], extrinsic[0, 0])
    ratios = (np.arange(width, 0, -1) - 0.5) / width
    return (ratios * 2.0 - 1.0) * np.pi - yaw_correction


def euler_to_rotation(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations R = Rz(yaw) Ry(pitch) Rx(roll) (Waymo's get_rotation_matrix)."""
    cr, sr, cp, sp, cy, sy = (np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch),
                              np.cos(yaw), np.sin(yaw))  # fmt: skip
    rotation = np.empty((*np.shape(roll), 3, 3))
    rotation[..., 0, 0] = cy * cp
    rotation[..., 0, 1] = cy * sp * sr - sy * cr
    rotation[..., 0, 2] = cy * sp * cr + sy * sr
    rotation[..., 1, 0] = sy * cp
    rotation[..., 1, 1] = sy * sp * sr + cy * cr
    rotation[..., 1, 2] = sy * sp * cr - cy * sr
    rotation[..., 2, 0] = -sp
    rotation[..., 2, 1] = cp * sr
    rotation[..., 2, 2] = cp * cr
    return rotation


def intensity_to_unit(intensity: np.ndarray) -> np.ndarray:
    """Waymo's raw intensity (>= 0, unbounded) → [0, 1): tanh, as OpenPCDet's Waymo loader does."""
    return np.tanh(np.maximum(np.asarray(intensity, np.float64), 0.0))


def range_image_to_points(
    range_image: np.ndarray,
    extrinsic: np.ndarray,
    inclinations: np.ndarray,
    pixel_pose: np.ndarray | None = None,
    frame_pose: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Points of one range image in the vehicle frame.

    range_image (H, W, >=2) float32; extrinsic (4, 4) LiDAR → vehicle; inclinations (H,) of the
    rows (see `row_inclinations`); pixel_pose (H, W, 6) and frame_pose (4, 4) vehicle → world,
    both or neither. Returns (points (N, 3) float64 vehicle frame, intensity (N,) raw) of the
    pixels with range > 0, in row-major order.
    """
    range_image = np.asarray(range_image)
    height, width = range_image.shape[:2]
    if len(inclinations) != height:
        raise ValueError(f"{len(inclinations)} inclinations for {height} rows")
    extrinsic = np.asarray(extrinsic, np.float64).reshape(4, 4)
    valid = range_image[..., 0] > 0  # (H, W)
    rows, cols = np.nonzero(valid)
    distance = range_image[rows, cols, 0].astype(np.float64)  # (N,)
    azimuth = column_azimuths(width, extrinsic)[cols]
    inclination = np.asarray(inclinations, np.float64)[rows]
    cos_inc = np.cos(inclination)
    local = (
        np.stack(
            [np.cos(azimuth) * cos_inc, np.sin(azimuth) * cos_inc, np.sin(inclination)], axis=1
        )
        * distance[:, None]
    )  # (N, 3) LiDAR frame
    points = local @ extrinsic[:3, :3].T + extrinsic[:3, 3]  # (N, 3) vehicle frame
    if (pixel_pose is None) != (frame_pose is None):
        raise ValueError("pixel_pose and frame_pose go together")
    if pixel_pose is not None:
        pose = np.asarray(pixel_pose, np.float64)[rows, cols]  # (N, 6)
        rotation = euler_to_rotation(pose[:, 0], pose[:, 1], pose[:, 2])  # (N, 3, 3)
        world = np.einsum("nij,nj->ni", rotation, points) + pose[:, 3:6]
        vehicle_from_world = np.linalg.inv(np.asarray(frame_pose, np.float64).reshape(4, 4))
        points = world @ vehicle_from_world[:3, :3].T + vehicle_from_world[:3, 3]
    return points, range_image[rows, cols, 1].astype(np.float64)
