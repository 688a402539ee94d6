"""Scanning a scene with a sensor profile's full ray pattern: the ground intersected analytically,
clutter as one Embree scene per frame, each car traced in its cached model BVH for the rays of its
angular window only; the first hit wins (cars occlude each other, clutter occludes cars); then
range noise, ray dropout, weak far echoes lost, min/max range and intensity from incidence,
material and surface texture."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from dali_cli.geometry import bev_corners, rotate_xy, wrap_angle
from dali_cli.raycast import Scene, cast, cast_into_box
from dali_cli.sensors import SensorProfile
from dali_cli.world.cars import body_box, pool_car
from dali_cli.world.scene import EGO_FOOTPRINT, SynthScene

# ---------------------------------------------------------------------------------------------
# Intensity and returns
#
# Calibrated against real KITTI HDL-64E scans (docs/synth.md): their intensity depends little on
# the angle of incidence (asphalt far ahead still returns ~0.25), varies from return to return on
# one surface, and dark surfaces far away often return nothing.

INCIDENCE_FLOOR = 0.6  # intensity at grazing incidence, as a share of the head-on one
TEXTURE_SIGMA = 0.25  # log-normal spread of a surface's reflectance from return to return
SIGNAL_REFERENCE_M = 10.0  # range at which the return probability depends on reflectance alone
# echo strength (intensity / (range / reference)^2) that returns with probability 1 - 1/e
SIGNAL_SCALE = 0.0015


EGO_BODY_HEIGHT_M = 0.65  # the ego car's hood and boot line above the ground (the roof is under the
# sensor): real KITTI scans lose most returns of the beams below about -20 deg in front to it


def ego_blocked(directions: np.ndarray, mount_height_m: float) -> np.ndarray:
    """`(N,)` bool: rays from the sensor `(N, 3)` that meet the ego car's body (EGO_FOOTPRINT up
    to EGO_BODY_HEIGHT_M) before anything else; they return nothing. The sensor sits above the
    footprint, so such a ray enters the body through its top face."""
    drop = mount_height_m - EGO_BODY_HEIGHT_M  # the top face below the sensor (m)
    down = directions[:, 2] < -1e-9
    t = np.full(len(directions), np.inf)
    t[down] = drop / -directions[down, 2]
    with np.errstate(invalid="ignore"):
        x, y = t * directions[:, 0], t * directions[:, 1]
        return down & (np.abs(x) < EGO_FOOTPRINT[3] / 2) & (np.abs(y) < EGO_FOOTPRINT[4] / 2)


def return_probability(intensity: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """Probability `(N,)` that a ray whose surface would give `intensity` `(N,)` at `distance`
    `(N,)` m returns: the echo falls with the squared range, weak echoes get lost."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        echo = intensity * (SIGNAL_REFERENCE_M / np.maximum(distance, 1e-3)) ** 2
        return 1.0 - np.exp(-np.nan_to_num(echo, nan=0.0) / SIGNAL_SCALE)


# ---------------------------------------------------------------------------------------------
# Scanning


@dataclass(frozen=True)
class _Pattern:
    directions: np.ndarray  # (B * P, 3) float64 unit, beam-major
    directions32: np.ndarray  # the same as float32 C-contiguous (Embree's input, no copy)
    elevations: np.ndarray  # (B,) ascending rad
    azimuth_start: float
    azimuth_step: float
    columns: int
    full_circle: bool


@lru_cache(maxsize=8)
def _pattern(sensor: SensorProfile) -> _Pattern:
    return _Pattern(
        directions=sensor.ray_pattern().directions.astype(np.float64),
        directions32=sensor.ray_pattern().directions,
        elevations=sensor.elevations_rad(),
        azimuth_start=float(np.radians(sensor.azimuth_min_deg)),
        azimuth_step=sensor.azimuth_step_rad,
        columns=sensor.points_per_beam,
        full_circle=sensor.azimuth_max_deg - sensor.azimuth_min_deg >= 360.0 - 1e-9,
    )


def box_ray_window(pattern: _Pattern, box: np.ndarray) -> np.ndarray:
    """Indices `(R,)` int64 of the pattern rays that can hit `box` (7,) seen from the origin.

    Azimuth bounds from the footprint corners; elevation bounds from the nearest and farthest
    footprint points (a box's top edge seen side-on peaks between corners), one ray of margin.
    """
    corners = bev_corners(box)[0]
    center_azimuth = np.arctan2(box[1], box[0])
    offsets = wrap_angle(np.arctan2(corners[:, 1], corners[:, 0]) - center_azimuth)
    # azimuth of the center counted from the pattern's first column, in [0, 2 pi)
    relative = np.mod(center_azimuth - pattern.azimuth_start, 2.0 * np.pi)
    low = int(np.floor((relative + offsets.min()) / pattern.azimuth_step)) - 1
    high = int(np.ceil((relative + offsets.max()) / pattern.azimuth_step)) + 1
    columns = np.arange(low, high + 1)
    if pattern.full_circle:
        columns = np.unique(columns % pattern.columns)
    else:  # a partial field of view: the box may also straddle its start, one turn earlier
        turn = int(round(2.0 * np.pi / pattern.azimuth_step))
        columns = np.concatenate([columns, columns - turn])
        columns = np.unique(columns[(columns >= 0) & (columns < pattern.columns)])
    c, s = np.cos(box[6]), np.sin(box[6])
    local = np.array(
        [-(c * box[0] + s * box[1]), -(-s * box[0] + c * box[1])]
    )  # sensor in box frame
    gap = np.maximum(np.abs(local) - box[3:5] / 2, 0.0)
    near = max(float(np.hypot(*gap)), 1e-3)
    far = float(np.linalg.norm(corners, axis=1).max())
    top, bottom = box[2] + box[5] / 2, box[2] - box[5] / 2
    high_elevation = np.arctan2(top, near if top > 0 else far)
    low_elevation = np.arctan2(bottom, near if bottom < 0 else far)
    beam_low = max(int(np.searchsorted(pattern.elevations, low_elevation)) - 1, 0)
    beam_high = min(
        int(np.searchsorted(pattern.elevations, high_elevation)) + 1, len(pattern.elevations) - 1
    )
    beams = np.arange(beam_low, beam_high + 1)
    return (beams[:, None] * pattern.columns + columns[None, :]).reshape(-1)


@dataclass
class Scan:
    """A scanned frame: points `(n, 4)` float32, owner `(n,)` int32 (car index, -1 ground, -2
    clutter), and per car: visible rays before dropout `(K,)`, unoccluded rays `(K,)`."""

    points: np.ndarray
    owner: np.ndarray
    car_visible_rays: np.ndarray
    car_unoccluded_rays: np.ndarray


def scan_scene(
    scene: SynthScene, sensor: SensorProfile, rng: np.random.Generator, threads: int = 1
) -> Scan:
    """First-hit scan of `scene` with the full pattern of `sensor` (see module docstring)."""
    pattern = _pattern(sensor)
    directions = pattern.directions  # (R, 3)
    count = len(directions)
    limit = sensor.max_range_m + 4.0 * sensor.range_noise_sigma_m + 0.5
    distance = scene.ground.intersect(directions, limit)  # (R,)
    owner = np.where(np.isfinite(distance), -1, -3).astype(np.int32)  # -3: no return
    cosine = np.zeros(count)
    reflect = np.zeros(count)

    static = Scene([(scene.clutter_vertices, scene.clutter_faces)])
    hits = cast(
        static,
        np.zeros(3),
        pattern.directions32,
        max_distance=np.minimum(distance, limit),
        threads=threads,
    )
    closer = hits.hit & (hits.distance < distance)
    distance[closer] = hits.distance[closer]
    owner[closer] = -2
    cosine[closer] = hits.cosine_incidence(directions)[closer]
    reflect[closer] = scene.face_reflectance[hits.primitive_id[closer]] * sensor.intensity_clutter

    unoccluded = np.zeros(len(scene.cars), np.int64)
    for k, box in enumerate(scene.cars):
        rays = box_ray_window(pattern, box)
        if len(rays) == 0:
            continue
        model = pool_car(int(scene.car_models[k]))
        car = cast_into_box(
            model.bvh(),
            np.zeros(3),
            directions[rays],
            body_box(box),
            max_distance=limit,
            threads=threads,
        )
        unoccluded[k] = int(car.hit.sum())
        win = car.hit & (car.distance < distance[rays])
        chosen = rays[win]
        distance[chosen] = car.distance[win]
        owner[chosen] = k
        cosine[chosen] = car.cosine_incidence(directions[rays])[win]
        # glass above the beltline returns less
        local_z = (car.points[win, 2] - box[2]) / box[5]
        glass = np.where(local_z > model.beltline_unit, 0.35, 1.0)
        reflect[chosen] = scene.car_reflectance[k] * sensor.intensity_car * glass

    ground = owner == -1
    if ground.any():
        xy = distance[ground, None] * directions[ground, :2]
        normal = scene.ground.normal()
        cosine[ground] = np.abs((directions[ground] * normal).sum(axis=1))
        lateral = rotate_xy(xy, -scene.road_heading)[:, 1]
        along = rotate_xy(xy, -scene.road_heading)[:, 0]
        marking = np.zeros(len(xy), bool)
        if len(scene.lane_lines):
            near_line = np.abs(lateral[:, None] - scene.lane_lines[None, :]).min(axis=1) < 0.08
            marking = near_line & ((along % 9.0) < 3.0)  # dashed lines
        reflect[ground] = sensor.intensity_ground * np.where(marking, 4.0, 1.0)

    owner[ego_blocked(directions, sensor.mount_height_m)] = -3
    visible = np.bincount(owner[owner >= 0], minlength=len(scene.cars))
    returned = owner != -3
    noisy = distance + rng.normal(0.0, sensor.range_noise_sigma_m, count)
    # a surface's own texture: each return's reflectance varies around its material's
    texture = rng.lognormal(-0.5 * TEXTURE_SIGMA**2, TEXTURE_SIGMA, count)
    intensity = reflect * texture * (INCIDENCE_FLOOR + (1.0 - INCIDENCE_FLOOR) * cosine)
    keep = returned & (rng.random(count) < return_probability(intensity, distance))
    keep &= rng.random(count) >= sensor.ray_dropout
    keep &= (noisy >= sensor.min_range_m) & (noisy <= sensor.max_range_m)
    intensity = intensity + rng.normal(0.0, 0.02, count)
    points = np.c_[noisy[keep, None] * directions[keep], np.clip(intensity[keep], 0.0, 1.0)]
    return Scan(
        points=points.astype(np.float32),
        owner=owner[keep],
        car_visible_rays=visible,
        car_unoccluded_rays=unoccluded,
    )
