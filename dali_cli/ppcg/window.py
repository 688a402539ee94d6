"""Angular windows: the azimuth/elevation rectangle a box covers, and the sensor rays inside it.

A ray from the sensor origin can only hit a box if its azimuth lies between the extreme azimuths
of the box footprint (reached at footprint corners) and its elevation between the extremes over
the box, which are reached on the top/bottom face at the footprint point nearest to the sensor
(or farthest, for a face on the other side of the sensor's horizontal plane). The nearest point is
usually on an edge, not a corner: a side-on car at 6 m loses rays when only corners are used.

The sensor pattern is a regular grid (ascending beam elevations x evenly spaced azimuth columns),
so the rays of a window are index ranges: no scan of the full pattern.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from dali_cli.columns import Columns
from dali_cli.geometry import wrap_angle
from dali_cli.sensors import SensorProfile

_EPS = 1e-9  # rad: rays exactly on a window edge are kept


@dataclass(frozen=True)
class AngularWindows(Columns):
    """Windows of N boxes, all `(N,)` float64 rad.

    azimuth_lo <= azimuth_hi, azimuth_lo in [-pi, pi), the span below 2 pi (it may end past pi);
    `full` marks boxes whose footprint contains the sensor (every azimuth, elevation +-pi/2).
    """

    azimuth_lo: np.ndarray
    azimuth_hi: np.ndarray
    elevation_lo: np.ndarray
    elevation_hi: np.ndarray
    full: np.ndarray


def footprint_distances(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal distance from the sensor to the nearest and farthest footprint point.

    boxes `(N, 7)` -> (near `(N,)`, far `(N,)`) metres; near is 0 when the sensor is inside.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    # sensor origin in box-local BEV coordinates: R^T (0 - centre)
    local_x = -(cos * boxes[:, 0] + sin * boxes[:, 1])
    local_y = -(-sin * boxes[:, 0] + cos * boxes[:, 1])
    half_l, half_w = 0.5 * boxes[:, 3], 0.5 * boxes[:, 4]
    out_x = np.maximum(np.abs(local_x) - half_l, 0.0)
    out_y = np.maximum(np.abs(local_y) - half_w, 0.0)
    near = np.hypot(out_x, out_y)
    far = np.hypot(np.abs(local_x) + half_l, np.abs(local_y) + half_w)
    return near, far


def box_windows(boxes: np.ndarray) -> AngularWindows:
    """Angular windows of boxes `(N, 7)` seen from the sensor origin (see module docstring)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    sign_l = np.array([1.0, 1.0, -1.0, -1.0])
    sign_w = np.array([1.0, -1.0, -1.0, 1.0])
    dx = 0.5 * boxes[:, 3:4] * sign_l  # (N, 4) corner offsets along the heading
    dy = 0.5 * boxes[:, 4:5] * sign_w  # (N, 4) and across it
    corner_x = boxes[:, 0:1] + cos[:, None] * dx - sin[:, None] * dy  # (N, 4)
    corner_y = boxes[:, 1:2] + sin[:, None] * dx + cos[:, None] * dy  # (N, 4)
    centre_azimuth = np.arctan2(boxes[:, 1], boxes[:, 0])  # (N,)
    relative = np.arctan2(corner_y, corner_x) - centre_azimuth[:, None]  # (N, 4)
    relative = wrap_angle(relative)
    near, far = footprint_distances(boxes)
    full = near <= 0.0
    azimuth_lo = np.where(full, -np.pi, centre_azimuth + relative.min(axis=1) - _EPS)
    azimuth_hi = np.where(full, np.pi, centre_azimuth + relative.max(axis=1) + _EPS)
    shift = np.where(
        azimuth_lo < -np.pi, 2.0 * np.pi, np.where(azimuth_lo >= np.pi, -2.0 * np.pi, 0.0)
    )
    azimuth_lo, azimuth_hi = azimuth_lo + shift, azimuth_hi + shift
    bottom = boxes[:, 2] - 0.5 * boxes[:, 5]
    top = boxes[:, 2] + 0.5 * boxes[:, 5]
    elevation_hi = np.arctan2(top, np.where(top >= 0.0, near, far)) + _EPS
    elevation_lo = np.arctan2(bottom, np.where(bottom <= 0.0, near, far)) - _EPS
    return AngularWindows(azimuth_lo, azimuth_hi, elevation_lo, elevation_hi, full)


def window_columns(profile: SensorProfile, azimuth_lo: float, azimuth_hi: float) -> np.ndarray:
    """Azimuth column indices `(C,)` int64 of `profile` whose azimuth lies in [lo, hi] mod 2 pi."""
    columns = profile.points_per_beam
    if azimuth_hi - azimuth_lo >= 2.0 * np.pi:
        return np.arange(columns, dtype=np.int64)
    step = profile.azimuth_step_rad
    start = np.radians(profile.azimuth_min_deg)
    parts = []
    for shift in (-2.0 * np.pi, 0.0, 2.0 * np.pi):  # the window may wrap past the pattern start
        first = max(int(np.ceil((azimuth_lo + shift - start) / step)), 0)
        last = min(int(np.floor((azimuth_hi + shift - start) / step)), columns - 1)
        if last >= first:
            parts.append(np.arange(first, last + 1, dtype=np.int64))
    if not parts:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.concatenate(parts)) if len(parts) > 1 else parts[0]


@lru_cache(maxsize=16)
def _tables(profile: SensorProfile) -> tuple[np.ndarray, ...]:
    """Per profile, once: elevations `(B,)` and cos/sin of elevations `(B,)` and azimuths `(P,)`."""
    elevation, azimuth = profile.elevations_rad(), profile.azimuths_rad()
    return elevation, np.cos(elevation), np.sin(elevation), np.cos(azimuth), np.sin(azimuth)


def window_beams(profile: SensorProfile, elevation_lo: float, elevation_hi: float) -> np.ndarray:
    """Beam indices `(B,)` int64 whose elevation lies in [lo, hi] (elevations are ascending)."""
    elevations = _tables(profile)[0]
    first = int(np.searchsorted(elevations, elevation_lo, side="left"))
    last = int(np.searchsorted(elevations, elevation_hi, side="right"))
    return np.arange(first, last, dtype=np.int64)


@dataclass(frozen=True)
class WindowRays:
    """Rays of one window: directions `(R, 3)` float64 unit vectors, beam and column `(R,)` int64.

    `index` `(R,)` is the position in the profile's beam-major RayPattern (beam * columns + column).
    """

    directions: np.ndarray
    beam: np.ndarray
    column: np.ndarray
    index: np.ndarray


def window_rays(
    profile: SensorProfile,
    azimuth_lo: float,
    azimuth_hi: float,
    elevation_lo: float,
    elevation_hi: float,
) -> WindowRays:
    """The profile's rays inside one angular window, built from index ranges (see WindowRays)."""
    beams = window_beams(profile, elevation_lo, elevation_hi)
    columns = window_columns(profile, azimuth_lo, azimuth_hi)
    _, cos_el, sin_el, cos_az, sin_az = _tables(profile)
    shape = (len(beams), len(columns))
    cos_el, sin_el = cos_el[beams, None], sin_el[beams, None]  # (B, 1)
    directions = np.empty(shape + (3,))  # (B, C, 3), as sensors.spherical_directions
    directions[..., 0] = cos_el * cos_az[columns]
    directions[..., 1] = cos_el * sin_az[columns]
    directions[..., 2] = np.broadcast_to(sin_el, shape)
    beam = np.repeat(beams, len(columns))
    column = np.tile(columns, len(beams))
    return WindowRays(
        directions.reshape(-1, 3), beam, column, beam * profile.points_per_beam + column
    )


@lru_cache(maxsize=16)
def _direction_table(profile: SensorProfile) -> np.ndarray:
    """Per profile, once: the unit direction of every ray `(B * P, 3)` float64, beam-major, each
    computed exactly as `window_rays` computes it (so a gather gives the same bits)."""
    _, cos_el, sin_el, cos_az, sin_az = _tables(profile)
    shape = (len(cos_el), len(cos_az))
    table = np.empty(shape + (3,))
    table[..., 0] = cos_el[:, None] * cos_az
    table[..., 1] = cos_el[:, None] * sin_az
    table[..., 2] = np.broadcast_to(sin_el[:, None], shape)
    table.flags.writeable = False
    return table.reshape(-1, 3)


def windows_directions(
    profile: SensorProfile, windows: AngularWindows
) -> tuple[np.ndarray, np.ndarray]:
    """The rays of every window, window after window: directions `(N, 3)` float64 (each window's
    rays in `window_rays` order, with the same values) and bounds `(k + 1,)` int64 (window i
    owns rays bounds[i]:bounds[i + 1]). One gather from the profile's direction table instead of
    building each window's directions: the per-box cost of CF's ray generation."""
    elevations = _tables(profile)[0]
    first = np.searchsorted(elevations, windows.elevation_lo, side="left")
    last = np.searchsorted(elevations, windows.elevation_hi, side="right")
    columns_per_beam = profile.points_per_beam
    parts = []
    for i in range(len(windows)):
        columns = window_columns(
            profile, float(windows.azimuth_lo[i]), float(windows.azimuth_hi[i])
        )
        beams = np.arange(first[i], last[i], dtype=np.int64)
        parts.append((beams[:, None] * columns_per_beam + columns).reshape(-1))
    counts = [len(part) for part in parts]
    bounds = np.zeros(len(parts) + 1, dtype=np.int64)
    np.cumsum(counts, out=bounds[1:])
    index = np.concatenate(parts) if parts else np.zeros(0, np.int64)
    return _direction_table(profile)[index], bounds
