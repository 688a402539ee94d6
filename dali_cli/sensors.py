"""The LiDAR sensor library: loads and validates sensors.toml profiles and builds ray patterns.

A profile describes one spinning LiDAR (beam elevations, azimuth sampling, mount height, range
limits, noise) plus the dataset's mean car size, which PTSN and SN use as target statistics.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from dali_cli import quantities
from dali_cli.runtime.errors import StageError
from dali_cli.runtime.limits import check_limit

DEFAULT_SENSORS_PATH = Path(__file__).resolve().parent.parent / "sensors.toml"

_REQUIRED = ("beams", "points_per_beam", "mount_height_m", "max_range_m", "car_mean_lwh_m")
_KNOWN = set(_REQUIRED) | {
    "description",
    "elevation_min_deg",
    "elevation_max_deg",
    "elevations_deg",
    "azimuth_min_deg",
    "azimuth_max_deg",
    "min_range_m",
    "range_noise_sigma_m",
    "ray_dropout",
    "intensity_car",
    "intensity_ground",
    "intensity_clutter",
    "car_std_lwh_m",
}


class SensorConfigError(StageError):
    """A sensors.toml problem; the message names the file, profile and key."""


@dataclass(frozen=True)
class SensorProfile:
    """One LiDAR profile. Angles in degrees, distances in metres."""

    name: str
    description: str
    elevations_deg: tuple[float, ...]  # (beams,) ascending
    points_per_beam: int
    azimuth_min_deg: float
    azimuth_max_deg: float
    mount_height_m: float
    max_range_m: float
    min_range_m: float
    range_noise_sigma_m: float
    ray_dropout: float
    intensity_car: float
    intensity_ground: float
    intensity_clutter: float
    car_mean_lwh_m: tuple[float, float, float]
    car_std_lwh_m: tuple[float, float, float]

    @property
    def beams(self) -> int:
        return len(self.elevations_deg)

    @property
    def num_rays(self) -> int:
        return self.beams * self.points_per_beam

    @property
    def azimuth_step_rad(self) -> float:
        """Angular spacing of consecutive azimuth samples (rad)."""
        return math.radians(self.azimuth_max_deg - self.azimuth_min_deg) / self.points_per_beam

    def azimuths_rad(self) -> np.ndarray:
        """Azimuth of each column, `(points_per_beam,)` float64, in [azimuth_min, azimuth_max)."""
        start = math.radians(self.azimuth_min_deg)
        return start + self.azimuth_step_rad * np.arange(self.points_per_beam, dtype=np.float64)

    def elevations_rad(self) -> np.ndarray:
        """Elevation of each beam, `(beams,)` float64, ascending."""
        return np.radians(np.asarray(self.elevations_deg, dtype=np.float64))

    def ray_pattern(self) -> RayPattern:
        return ray_pattern(self)


@dataclass(frozen=True)
class RayPattern:
    """All rays of one revolution, beam-major.

    directions: `(beams * points_per_beam, 3)` float32 unit vectors in the sensor frame.
    beam: `(N,)` int32 beam (row) index; azimuth_index: `(N,)` int32 column index.
    """

    directions: np.ndarray
    beam: np.ndarray
    azimuth_index: np.ndarray


def spherical_directions(elevation_rad: np.ndarray, azimuth_rad: np.ndarray) -> np.ndarray:
    """Unit vectors for elevation/azimuth arrays of equal shape `(...)` → `(..., 3)` float64."""
    cos_el = np.cos(elevation_rad)
    return np.stack(
        [cos_el * np.cos(azimuth_rad), cos_el * np.sin(azimuth_rad), np.sin(elevation_rad)],
        axis=-1,
    )


def ray_pattern(profile: SensorProfile) -> RayPattern:
    """Build the full ray pattern of `profile` (see RayPattern)."""
    elevation = profile.elevations_rad()  # (B,)
    azimuth = profile.azimuths_rad()  # (P,)
    el_grid, az_grid = np.meshgrid(elevation, azimuth, indexing="ij")  # (B, P)
    directions = spherical_directions(el_grid, az_grid).reshape(-1, 3)  # (B*P, 3)
    beam, column = np.meshgrid(
        np.arange(profile.beams, dtype=np.int32),
        np.arange(profile.points_per_beam, dtype=np.int32),
        indexing="ij",
    )
    return RayPattern(
        directions=np.ascontiguousarray(directions, dtype=np.float32),
        beam=beam.reshape(-1),
        azimuth_index=column.reshape(-1),
    )


def _fail(source: str, profile: str, key: str, problem: str) -> SensorConfigError:
    return SensorConfigError(f"{source}: profile [{profile}] key '{key}': {problem}")


def _number(
    table: dict,
    key: str,
    source: str,
    name: str,
    default: float | None = None,
    kind: quantities.Quantity | None = None,
) -> float:
    """The finite number at `key` (of `kind` when given: its physical range)."""
    if key not in table:
        if default is None:
            raise _fail(source, name, key, "missing")
        return float(default)
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise _fail(source, name, key, f"must be a finite number, got {value!r}")
    problem = kind.problem(value) if kind is not None else None
    if problem is not None:
        raise _fail(source, name, key, problem)
    return float(value)


def _triple(
    table: dict, key: str, source: str, name: str, kind: quantities.Quantity, default=None
) -> tuple[float, ...]:
    """[l, w, h] at `key`: three numbers of `kind` (metres)."""
    if key not in table:
        if default is None:
            raise _fail(source, name, key, "missing")
        return tuple(default)
    try:
        return quantities.check_triple(kind, table[key], "")
    except quantities.QuantityError as error:
        raise _fail(source, name, key, str(error).removeprefix(": ")) from None


def _positive_int(table: dict, key: str, source: str, name: str) -> int:
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise _fail(source, name, key, f"must be an integer > 0, got {value!r}")
    return value


def _elevations(table: dict, beams: int, source: str, name: str) -> list[float]:
    """The beams' elevations (deg, ascending): listed, or evenly spaced from min to max."""
    if "elevations_deg" in table:
        elevations = table["elevations_deg"]
        if not isinstance(elevations, list) or len(elevations) != beams:
            raise _fail(source, name, "elevations_deg", f"must list exactly beams={beams} angles")
        if not all(isinstance(e, int | float) and not isinstance(e, bool) for e in elevations):
            raise _fail(source, name, "elevations_deg", "must contain numbers only")
        elevations = sorted(float(e) for e in elevations)
        if any(not -90.0 < e < 90.0 for e in elevations):
            raise _fail(source, name, "elevations_deg", "angles must lie in (-90, 90)")
        return elevations
    low = _number(table, "elevation_min_deg", source, name)
    high = _number(table, "elevation_max_deg", source, name)
    if not low < high:
        raise _fail(
            source, name, "elevation_min_deg", f"must be < elevation_max_deg ({low} >= {high})"
        )
    if low <= -90.0 or high >= 90.0:
        raise _fail(source, name, "elevation_min_deg", "elevations must lie in (-90, 90)")
    return np.linspace(low, high, beams).tolist() if beams > 1 else [0.5 * (low + high)]


def _ranges_and_noise(table: dict, source: str, name: str) -> dict:
    """mount_height_m, max/min_range_m, range_noise_sigma_m, ray_dropout, checked."""
    mount = _number(table, "mount_height_m", source, name, kind=quantities.MOUNT_HEIGHT_M)
    max_range = _number(table, "max_range_m", source, name, kind=quantities.DISTANCE_M)
    min_range = _number(table, "min_range_m", source, name, 0.0)
    if max_range <= 0:
        raise _fail(source, name, "max_range_m", f"must be > 0, got {max_range}")
    if not 0 <= min_range < max_range:
        raise _fail(
            source, name, "min_range_m", f"must satisfy 0 <= min_range < max_range ({max_range})"
        )
    noise = _number(table, "range_noise_sigma_m", source, name, 0.0, quantities.RANGE_NOISE_M)
    dropout = _number(table, "ray_dropout", source, name, 0.0)
    if not 0.0 <= dropout < 1.0:
        raise _fail(source, name, "ray_dropout", f"must satisfy 0 <= dropout < 1, got {dropout}")
    return {
        "mount_height_m": mount,
        "max_range_m": max_range,
        "min_range_m": min_range,
        "range_noise_sigma_m": noise,
        "ray_dropout": dropout,
    }


def _intensities(table: dict, source: str, name: str) -> dict:
    intensities = {}
    for key, default in (
        ("intensity_car", 0.3),
        ("intensity_ground", 0.1),
        ("intensity_clutter", 0.4),
    ):
        value = _number(table, key, source, name, default)
        if not 0.0 <= value <= 1.0:
            raise _fail(source, name, key, f"must lie in [0, 1], got {value}")
        intensities[key] = value
    return intensities


def parse_profile(name: str, table: dict, source: str = "<sensors>") -> SensorProfile:
    """Validate one TOML table and build a SensorProfile; errors name source, profile and key."""
    if not isinstance(table, dict):
        raise _fail(source, name, "-", "profile must be a table")
    unknown = sorted(set(table) - _KNOWN)
    if unknown:
        raise _fail(source, name, unknown[0], f"unknown key (known: {', '.join(sorted(_KNOWN))})")
    for key in _REQUIRED:
        if key not in table:
            raise _fail(source, name, key, "missing")
    beams = _positive_int(table, "beams", source, name)
    points_per_beam = _positive_int(table, "points_per_beam", source, name)
    check_limit(
        "rays_per_frame",
        beams * points_per_beam,
        f"{source}: profile [{name}] keys 'beams' x 'points_per_beam'",
    )
    elevations = _elevations(table, beams, source, name)
    az_min = _number(table, "azimuth_min_deg", source, name, -180.0)
    az_max = _number(table, "azimuth_max_deg", source, name, 180.0)
    if not az_min < az_max or az_max - az_min > 360.0:
        raise _fail(source, name, "azimuth_min_deg", "need azimuth_min < azimuth_max, span <= 360")
    ranges = _ranges_and_noise(table, source, name)
    intensities = _intensities(table, source, name)
    mean_lwh = _triple(table, "car_mean_lwh_m", source, name, quantities.CAR_SIZE_M)
    spread = quantities.SIZE_SPREAD_M
    std_lwh = _triple(table, "car_std_lwh_m", source, name, spread, [0.08 * v for v in mean_lwh])
    description = table.get("description", "")
    if not isinstance(description, str):
        raise _fail(source, name, "description", "must be a string")
    return SensorProfile(
        name=name,
        description=description,
        elevations_deg=tuple(float(e) for e in elevations),
        points_per_beam=points_per_beam,
        azimuth_min_deg=az_min,
        azimuth_max_deg=az_max,
        car_mean_lwh_m=mean_lwh,
        car_std_lwh_m=std_lwh,
        **ranges,
        **intensities,
    )


def load_profiles(path: str | Path | None = None) -> dict[str, SensorProfile]:
    """Load every profile of a sensors.toml (default: the project's). Errors name file and key."""
    path = Path(path) if path is not None else DEFAULT_SENSORS_PATH
    from dali_cli.store.regular_files import UnreadableFileError, read_text_file

    try:
        text = read_text_file(path, "sensor file", "toml")
    except UnreadableFileError as error:  # missing, a directory, too large, not UTF-8
        raise SensorConfigError(str(error)) from None
    except OSError as error:
        raise SensorConfigError(f"{path}: cannot read sensor file ({error})") from None
    return dict(_parse_cached(str(path), text))


@lru_cache(maxsize=8)
def _parse_cached(source: str, text: str) -> tuple[tuple[str, SensorProfile], ...]:
    """Parsing is cached by (path, content), so an edited file is re-read."""
    try:
        document = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise SensorConfigError(f"{source}: invalid TOML ({error})") from None
    if not document:
        raise SensorConfigError(f"{source}: no sensor profiles defined")
    return tuple((name, parse_profile(name, table, source)) for name, table in document.items())


def get_profile(name: str, path: str | Path | None = None) -> SensorProfile:
    """One profile by name; an unknown name is an error listing the available ones."""
    profiles = load_profiles(path)
    if name not in profiles:
        source = Path(path) if path is not None else DEFAULT_SENSORS_PATH
        raise SensorConfigError(
            f"{source}: unknown sensor profile '{name}' (available: {', '.join(sorted(profiles))})"
        )
    return profiles[name]
