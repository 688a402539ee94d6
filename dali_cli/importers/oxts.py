"""KITTI raw OXTS (GPS/IMU) records turned into LiDAR poses: where each scan's Velodyne frame
sits in the Velodyne frame of the drive's first scan.

`oxts/data/<index>.txt` holds one line of 30 values (the raw devkit's `dataformat.txt`): lat,
lon (degrees), alt (m), roll, pitch, yaw (rad), then velocities, accelerations, rates, accuracy
and status fields, which are read but not used here. The devkit's `convertOxtsToPose.m` puts
each record on a Mercator map scaled at the first record's latitude (x east, y north, z up) with
the rotation Rz(yaw) Ry(pitch) Rx(roll); `calib_imu_to_velo.txt` (R, T: x_velo = R x_imu + T)
moves that IMU pose onto the Velodyne.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dali_cli.importers.common import ImportFormatError, read_text_lines

OXTS_FIELDS = (
    "lat", "lon", "alt", "roll", "pitch", "yaw", "vn", "ve", "vf", "vl", "vu",
    "ax", "ay", "az", "af", "al", "au", "wx", "wy", "wz", "wf", "wl", "wu",
    "pos_accuracy", "vel_accuracy", "navstat", "numsats", "posmode", "velmode", "orimode",
)  # fmt: skip
EARTH_RADIUS_M = 6378137.0  # the devkit's er


def read_oxts(path: str | Path) -> np.ndarray:
    """`(30,)` float64 of one OXTS record file; errors name the file and the field."""
    path = Path(path)
    lines = [line for line in read_text_lines(path, "OXTS record") if line.strip()]
    if len(lines) != 1:
        raise ImportFormatError(f"{path}: an OXTS record is one line, the file has {len(lines)}")
    fields = lines[0].split()
    if len(fields) < 6:
        missing = OXTS_FIELDS[len(fields)]
        raise ImportFormatError(
            f"{path}: OXTS field '{missing}' missing ({len(fields)} values, expected 30)"
        )
    values = np.full(len(OXTS_FIELDS), np.nan)
    for index, text in enumerate(fields[: len(OXTS_FIELDS)]):
        name = OXTS_FIELDS[index]
        try:
            values[index] = float(text)
        except ValueError:
            raise ImportFormatError(
                f"{path}: OXTS field '{name}' is not a number ({text!r})"
            ) from None
        if index < 6 and not np.isfinite(values[index]):
            raise ImportFormatError(f"{path}: OXTS field '{name}' is NaN/inf")
    if abs(values[0]) >= 90:
        raise ImportFormatError(f"{path}: OXTS field 'lat' is {values[0]}, outside (-90, 90)")
    return values


def rotation_rpy(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """`(n, 3, 3)` Rz(yaw) @ Ry(pitch) @ Rx(roll) of `(n,)` angles in radians."""
    cr, sr, cp, sp, cy, sy = (f(a) for a in (roll, pitch, yaw) for f in (np.cos, np.sin))
    return np.stack(
        [
            np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], axis=-1),
            np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], axis=-1),
            np.stack([-sp, cp * sr, cp * cr], axis=-1),
        ],
        axis=-2,
    )  # (n, 3, 3)


def oxts_imu_poses(records: np.ndarray) -> np.ndarray:
    """`(n, 4, 4)` IMU poses on the devkit's Mercator map (x east, y north, z up, metres) of
    `(n, >= 6)` OXTS records, the map scaled at the first record's latitude."""
    lat, lon, alt = records[:, 0], records[:, 1], records[:, 2]
    scale = np.cos(np.radians(lat[0]))
    x = scale * np.radians(lon) * EARTH_RADIUS_M
    y = scale * EARTH_RADIUS_M * np.log(np.tan(np.radians(90.0 + lat) / 2))
    poses = np.tile(np.eye(4), (len(records), 1, 1))
    poses[:, :3, :3] = rotation_rpy(records[:, 3], records[:, 4], records[:, 5])
    poses[:, :3, 3] = np.c_[x, y, alt]
    return poses


def lidar_poses(imu_poses: np.ndarray, imu_to_velo: np.ndarray) -> np.ndarray:
    """`(n, 4, 4)` pose of each scan's Velodyne frame in the first scan's Velodyne frame:
    T_v0_vi = T_velo_imu inv(T_imu0) T_imu_i inv(T_velo_imu). `imu_to_velo`: `(4, 4)`
    x_velo = imu_to_velo @ x_imu."""
    velo_to_imu = np.linalg.inv(imu_to_velo)
    relative = np.linalg.inv(imu_poses[0]) @ imu_poses  # (n, 4, 4) IMU i in IMU 0
    return imu_to_velo @ relative @ velo_to_imu


def drive_lidar_poses(oxts_dir: str | Path, imu_to_velo: np.ndarray, frame_ids: list[str]):
    """`(n, 4, 4)` LiDAR poses of the scans `frame_ids` (each `<oxts_dir>/<id>.txt`), in the
    Velodyne frame of the first of them."""
    oxts_dir = Path(oxts_dir)
    records = np.stack([read_oxts(oxts_dir / f"{frame_id}.txt") for frame_id in frame_ids])
    return lidar_poses(oxts_imu_poses(records), imu_to_velo)
