"""Test fixture (tests and bench/detector.py, not part of the package). Tiny synthetic scenes: box-shaped cars on a flat ground, scanned with a
sensor profile's beams by an exact numpy ray/box (slab) intersection. Not `dali synth` (no meshes,
no clutter): just enough structure to check that the detector learns and that its I/O is right."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dali_cli.sensors import SensorProfile, spherical_directions
from dali_cli.store.artifacts import BoxTable, write_boxes, write_frameset

# a small detector configuration (a 25.6 m x 25.6 m grid, narrow layers) for fast tests
SMALL_NET = dict(
    x_range_m=(0.0, 25.6),
    y_range_m=(-12.8, 12.8),
    pfn_channels=16,
    block_channels=(16, 32, 64),
    block_layers=(1, 2, 2),
    up_channels=16,
    head_channels=32,
)


def place_cars(
    rng: np.random.Generator,
    count: int,
    mean_lwh: tuple[float, float, float],
    mount_height_m: float,
    x_range_m: tuple[float, float] = (5.0, 45.0),
    y_range_m: tuple[float, float] = (-20.0, 20.0),
) -> np.ndarray:
    """Up to `count` non-overlapping boxes (m, 7) in the sensor frame, standing on the ground."""
    boxes = []
    for _ in range(count * 10):  # rejection sampling over a handful of cars
        if len(boxes) == count:
            break
        lwh = np.asarray(mean_lwh) * rng.uniform(0.9, 1.1, 3)
        x, y = rng.uniform(*x_range_m), rng.uniform(*y_range_m)
        radius = np.hypot(lwh[0], lwh[1]) / 2
        if any(
            np.hypot(x - b[0], y - b[1]) < radius + np.hypot(b[3], b[4]) / 2 + 0.3 for b in boxes
        ):
            continue
        boxes.append([x, y, -mount_height_m + lwh[2] / 2, *lwh, rng.uniform(-np.pi, np.pi)])
    return np.asarray(boxes, np.float64).reshape(-1, 7)


def cabin_parts(boxes: np.ndarray) -> np.ndarray:
    """Each car box (m, 7) as two solid parts (2m, 7) inside it, a body over its whole length up to
    60 % of its height and a cabin on the rear 55 % above it: a car whose front (the end of +yaw,
    the low bonnet) a detector can tell from its back."""
    body, cabin = boxes.copy(), boxes.copy()
    body[:, 5] = 0.6 * boxes[:, 5]
    body[:, 2] = boxes[:, 2] - 0.2 * boxes[:, 5]
    cabin[:, 3] = 0.55 * boxes[:, 3]
    cabin[:, 5] = 0.4 * boxes[:, 5]
    cabin[:, 2] = boxes[:, 2] + 0.3 * boxes[:, 5]
    back = -0.225 * boxes[:, 3]  # the cabin's centre, along the car's heading
    cabin[:, 0] = boxes[:, 0] + back * np.cos(boxes[:, 6])
    cabin[:, 1] = boxes[:, 1] + back * np.sin(boxes[:, 6])
    return np.concatenate([body, cabin])


def scan(
    boxes: np.ndarray,
    profile: SensorProfile,
    azimuth_range_deg: tuple[float, float] = (-90.0, 90.0),
    beams: int | None = None,
    points_per_beam: int | None = None,
    cabins: bool = False,
) -> np.ndarray:
    """Scan boxes (m, 7) and the ground with the profile's beam pattern; returns (n, 4) float32
    first hits in the sensor frame with a constant intensity per surface. `cabins`: each car
    is a body and a cabin on its rear (`cabin_parts`), so its front shows."""
    if cabins:
        boxes = cabin_parts(np.asarray(boxes, np.float64).reshape(-1, 7))
    beams = beams or profile.beams
    columns = points_per_beam or round(
        profile.points_per_beam * (azimuth_range_deg[1] - azimuth_range_deg[0]) / 360
    )
    elevation = np.linspace(
        *np.radians([profile.elevations_deg[0], profile.elevations_deg[-1]]), beams
    )
    azimuth = np.linspace(*np.radians(azimuth_range_deg), columns, endpoint=False)
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    directions = spherical_directions(el, az).reshape(-1, 3)  # (R, 3)
    distance = np.full(len(directions), np.inf)  # (R,)
    intensity = np.zeros(len(directions))
    down = directions[:, 2] < -1e-6
    distance[down] = -profile.mount_height_m / directions[down, 2]
    intensity[down] = profile.intensity_ground
    for box in boxes:  # boxes: a few per scene; each tested against all rays at once
        cos, sin = np.cos(-box[6]), np.sin(-box[6])
        origin = -box[:3]  # sensor at the origin, in box-centered coordinates
        o = np.array(
            [cos * origin[0] - sin * origin[1], sin * origin[0] + cos * origin[1], origin[2]]
        )
        d = np.stack(
            [
                cos * directions[:, 0] - sin * directions[:, 1],
                sin * directions[:, 0] + cos * directions[:, 1],
                directions[:, 2],
            ],
            axis=1,
        )  # (R, 3)
        half = box[3:6] / 2
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-half - o) / d, (half - o) / d  # (R, 3)
        t_near = np.nanmax(np.minimum(t1, t2), axis=1)
        t_far = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (t_near <= t_far) & (t_near > 0) & (t_near < distance)
        distance[hit] = t_near[hit]
        intensity[hit] = profile.intensity_car
    valid = (distance < profile.max_range_m) & (distance > profile.min_range_m)
    xyz = directions[valid] * distance[valid, None]
    return np.concatenate([xyz, intensity[valid, None]], axis=1).astype(np.float32)


def write_toy_dataset(
    directory: str | Path,
    profile: SensorProfile,
    frames: int,
    seed: int,
    cars_per_frame: int = 8,
    mean_lwh: tuple[float, float, float] | None = None,
    x_range_m: tuple[float, float] = (5.0, 45.0),
    y_range_m: tuple[float, float] = (-20.0, 20.0),
    **scan_options,
) -> BoxTable:
    """Write a FrameSet + boxes.parquet of `frames` toy scenes into `directory`; returns the boxes."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    mean_lwh = mean_lwh or profile.car_mean_lwh_m
    scenes, ids, all_boxes = [], [], []
    for i in range(frames):
        rng = np.random.default_rng([seed, i])
        boxes = place_cars(
            rng, cars_per_frame, mean_lwh, profile.mount_height_m, x_range_m, y_range_m
        )
        frame_id = f"{i:06d}"
        scenes.append((frame_id, scan(boxes, profile, **scan_options)))
        ids += [frame_id] * len(boxes)
        all_boxes.append(boxes)
    write_frameset(directory, scenes, sensor=profile.name, attrs={"source": "detector.toy"})
    table = BoxTable.from_arrays(np.asarray(ids), np.concatenate(all_boxes))
    write_boxes(directory, table)
    return table
