"""A small analytic street scanned from a known trajectory (a test helper): ground, building
fronts with gaps and setbacks, poles and parked cars, cast with dali's ray caster from a
32-beam 360-degree LiDAR; the scans' points are in each scan's LiDAR frame."""

from __future__ import annotations

import functools

import numpy as np

from dali_cli.raycast import Scene
from dali_cli.world.scene import _box_mesh


@functools.cache
def street_scene(seed: int = 0) -> Scene:
    rng = np.random.default_rng(seed)
    boxes = [np.array([100.0, 0.0, -1.83, 400.0, 80.0, 0.2, 0.0])]  # ground, top at z = -1.73
    for side in (-1, 1):
        x = -60.0
        while x < 260:
            length = rng.uniform(8, 25)
            setback = rng.uniform(9, 15)
            height = rng.uniform(4, 12)
            boxes.append(np.array([x + length / 2, side * (setback + 3), height / 2 - 1.73,
                                   length, 6.0, height, 0.0]))  # fmt: skip
            x += length + rng.uniform(1, 6)
    for _ in range(60):  # poles and parked cars along the kerbs
        x, side = rng.uniform(-50, 250), rng.choice([-1, 1])
        if rng.random() < 0.5:
            boxes.append(np.array([x, side * rng.uniform(5, 7), 0.27, 0.3, 0.3, 4.0, 0.0]))
        else:
            boxes.append(np.array([x, side * 4.5, -0.98, 4.2, 1.8, 1.5, rng.normal(0, 0.1)]))
    return Scene([_box_mesh(box) for box in boxes])


def trajectory(
    steps_m: np.ndarray, yaw_rate: float = 0.01, yaw: np.ndarray | None = None
) -> np.ndarray:
    """`(n, 4, 4)` sensor poses in the street's frame: forward steps `steps_m` `(n - 1,)` (m),
    turning by `yaw_rate` (rad) a scan, or heading `yaw` `(n,)` (rad) when given, the sensor
    1.73 m above the ground."""
    steps_m = np.asarray(steps_m, np.float64)
    yaw = yaw_rate * np.arange(len(steps_m) + 1) if yaw is None else np.asarray(yaw, np.float64)
    heading = np.c_[np.cos(yaw[:-1]), np.sin(yaw[:-1])]
    xy = np.r_[[[0.0, 0.0]], np.cumsum(heading * np.asarray(steps_m)[:, None], axis=0)]
    poses = np.tile(np.eye(4), (len(yaw), 1, 1))
    c, s = np.cos(yaw), np.sin(yaw)
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = c, -s, s, c
    poses[:, :2, 3] = xy
    return poses


def lidar_rays(beams: int = 32, azimuth_deg: float = 0.6) -> np.ndarray:
    """`(r, 3)` unit directions: `beams` elevations in [-24, 4] deg, every `azimuth_deg`."""
    elevation = np.radians(np.linspace(-24, 4, beams))[:, None]
    azimuth = np.radians(np.arange(0, 360, azimuth_deg))[None, :]
    return np.stack(
        np.broadcast_arrays(np.cos(elevation) * np.cos(azimuth),
                            np.cos(elevation) * np.sin(azimuth), np.sin(elevation)),
        axis=-1,
    ).reshape(-1, 3)  # fmt: skip


def scan(pose: np.ndarray, seed: int = 0, noise_m: float = 0.01) -> np.ndarray:
    """`(n, 4)` float32 points (x, y, z in the LiDAR frame at `pose`, intensity 0.5) of the
    street scanned from `pose` `(4, 4)`, with Gaussian range noise."""
    rays = lidar_rays()
    hits = street_scene().cast(np.broadcast_to(pose[:3, 3], rays.shape), rays @ pose[:3, :3].T,
                               max_distance=100.0)  # fmt: skip
    rng = np.random.default_rng(seed)
    distance = hits.distance[hits.hit] + rng.normal(0, noise_m, hits.hit.sum())
    local = rays[hits.hit] * distance[:, None]
    return np.c_[local, np.full(len(local), 0.5)].astype(np.float32)


def step_errors(estimated: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(n - 1,)` translation (m) and rotation (deg) error of each scan-to-scan step of the poses
    `estimated` `(n, 4, 4)` against `truth`."""
    step = np.linalg.inv(estimated[:-1]) @ estimated[1:]
    true_step = np.linalg.inv(truth[:-1]) @ truth[1:]
    error = np.linalg.inv(true_step) @ step  # (n - 1, 4, 4)
    cosine = (np.trace(error[:, :3, :3], axis1=1, axis2=2) - 1) / 2
    return np.linalg.norm(error[:, :3, 3], axis=1), np.degrees(np.arccos(np.clip(cosine, -1, 1)))
