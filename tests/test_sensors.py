"""sensors.toml loading, validation messages and ray patterns."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.sensors import SensorConfigError, get_profile, load_profiles, parse_profile

METHOD_TABLE = {  # docs/method.md, dataset profiles
    "kitti": (64, -23.6, 3.2, 1843, (3.89, 1.62, 1.53)),
    "waymo": (64, -18.0, 2.0, 2500, (4.66, 2.08, 1.73)),
    "nuscenes": (32, -30.0, 10.0, 781, (4.63, 1.96, 1.73)),
}


@pytest.mark.parametrize("name", sorted(METHOD_TABLE))
def test_profiles_match_method_table(name):
    beams, low, high, per_beam, lwh = METHOD_TABLE[name]
    profile = get_profile(name)
    assert profile.beams == beams and profile.points_per_beam == per_beam
    assert profile.elevations_deg[0] == pytest.approx(low) and profile.elevations_deg[
        -1
    ] == pytest.approx(high)
    assert profile.car_mean_lwh_m == pytest.approx(lwh)


@pytest.mark.parametrize("name", sorted(METHOD_TABLE))
def test_ray_pattern_shape_unit_length_and_elevations(name):
    profile = get_profile(name)
    pattern = profile.ray_pattern()
    count = profile.beams * profile.points_per_beam
    assert pattern.directions.shape == (count, 3) and pattern.directions.dtype == np.float32
    assert pattern.directions.flags.c_contiguous
    np.testing.assert_allclose(np.linalg.norm(pattern.directions, axis=1), 1.0, atol=1e-6)
    elevation = np.degrees(np.arcsin(pattern.directions[:, 2].astype(np.float64)))
    low, high = profile.elevations_deg[0], profile.elevations_deg[-1]
    assert elevation.min() == pytest.approx(low, abs=1e-4) and elevation.max() == pytest.approx(
        high, abs=1e-4
    )
    # beam index decides elevation; azimuth index decides azimuth
    np.testing.assert_allclose(
        elevation, np.asarray(profile.elevations_deg)[pattern.beam], atol=1e-4
    )
    azimuth = np.arctan2(pattern.directions[:, 1], pattern.directions[:, 0]).astype(np.float64)
    expected = profile.azimuths_rad()[pattern.azimuth_index]
    wrapped = np.angle(np.exp(1j * (azimuth - expected)))
    assert np.abs(wrapped).max() < 1e-5
    # evenly spaced beams, all distinct columns
    assert np.allclose(np.diff(profile.elevations_deg), (high - low) / (profile.beams - 1))
    assert len(np.unique(pattern.azimuth_index)) == profile.points_per_beam


def write_toml(tmp_path, body: str):
    path = tmp_path / "sensors.toml"
    path.write_text(body)
    return path


GOOD = """
[mini]
beams = 4
elevation_min_deg = -10.0
elevation_max_deg = 2.0
points_per_beam = 8
mount_height_m = 1.5
max_range_m = 50.0
car_mean_lwh_m = [4.0, 1.8, 1.5]
"""


def test_custom_file_and_explicit_elevations(tmp_path):
    path = write_toml(
        tmp_path,
        GOOD
        + "\n[listed]\n"
        + "\n".join(GOOD.splitlines()[2:]).replace(
            "elevation_min_deg = -10.0\nelevation_max_deg = 2.0",
            "elevations_deg = [2.0, -10.0, -1.0, -3.5]",
        ),
    )
    profiles = load_profiles(path)
    assert set(profiles) == {"mini", "listed"}
    assert profiles["listed"].elevations_deg == (-10.0, -3.5, -1.0, 2.0)
    assert profiles["mini"].ray_pattern().directions.shape == (32, 3)
    assert profiles["mini"].ray_dropout == 0.0  # default


@pytest.mark.parametrize(
    ("edit", "key", "problem"),
    [
        (("beams = 4", "beams = 0"), "beams", "integer > 0"),
        (("beams = 4", "beams = 2.5"), "beams", "integer > 0"),
        (
            ("elevation_min_deg = -10.0", "elevation_min_deg = 5.0"),
            "elevation_min_deg",
            "must be <",
        ),
        (
            ("max_range_m = 50.0", "max_range_m = 50.0\nray_dropout = 1.0"),
            "ray_dropout",
            "0 <= dropout < 1",
        ),
        (("max_range_m = 50.0", "max_range_m = -1.0"), "max_range_m", "[0.1, 10000] m"),
        (
            ("car_mean_lwh_m = [4.0, 1.8, 1.5]", "car_mean_lwh_m = [4.0, 1.8]"),
            "car_mean_lwh_m",
            "3 numbers",
        ),
        (
            ("car_mean_lwh_m = [4.0, 1.8, 1.5]", "car_mean_lwh_m = [1e30, 1.8, 1.5]"),
            "car_mean_lwh_m",
            "[0.1, 30] m",
        ),
        (
            (
                "car_mean_lwh_m = [4.0, 1.8, 1.5]",
                "car_mean_lwh_m = [4.0, 1.8, 1.5]\ncar_std_lwh_m = [1e30, 0.1, 0.1]",
            ),
            "car_std_lwh_m",
            "[0, 10] m",
        ),
        (
            ("max_range_m = 50.0", "max_range_m = 50.0\nrange_noise_sigma_m = 1e30"),
            "range_noise_sigma_m",
            "[0, 1] m",
        ),
        (("points_per_beam = 8\n", ""), "points_per_beam", "missing"),
        (("beams = 4", "beams = 4\nbeam_count = 3"), "beam_count", "unknown key"),
        (("mount_height_m = 1.5", "mount_height_m = 'high'"), "mount_height_m", "finite number"),
    ],
)
def test_validation_names_file_profile_and_key(tmp_path, edit, key, problem):
    path = write_toml(tmp_path, GOOD.replace(*edit))
    with pytest.raises(SensorConfigError) as error:
        load_profiles(path)
    message = error.value.message
    assert (
        str(path) in message
        and "[mini]" in message
        and f"'{key}'" in message
        and problem in message
    )


def test_file_errors(tmp_path):
    with pytest.raises(SensorConfigError, match="not found"):
        load_profiles(tmp_path / "absent.toml")
    with pytest.raises(SensorConfigError, match="invalid TOML"):
        load_profiles(write_toml(tmp_path, "[x\n"))
    with pytest.raises(SensorConfigError, match="unknown sensor profile 'velodyne'.*kitti"):
        get_profile("velodyne")


def test_parse_profile_rejects_list_with_wrong_length():
    with pytest.raises(SensorConfigError, match="exactly beams=2"):
        parse_profile(
            "p",
            {
                "beams": 2,
                "elevations_deg": [1.0],
                "points_per_beam": 4,
                "mount_height_m": 1.0,
                "max_range_m": 10.0,
                "car_mean_lwh_m": [4, 2, 1.5],
            },
        )


def test_sensors_command_lists_profiles(tmp_path):
    runner = CliRunner()
    result = runner.invoke(main, ["sensors"])
    assert result.exit_code == 0, result.output
    for name in METHOD_TABLE:
        assert name in result.output
    assert "117952" in result.output  # kitti rays: 64 * 1843
    result = runner.invoke(main, ["sensors", "--sensors", str(write_toml(tmp_path, GOOD))])
    assert result.exit_code == 0 and "mini" in result.output and "kitti" not in result.output
    bad = write_toml(tmp_path, GOOD.replace("beams = 4", "beams = -4"))
    result = runner.invoke(main, ["sensors", "--sensors", str(bad)])
    assert result.exit_code == 1 and "'beams'" in result.output and "Traceback" not in result.output


def test_waymo_top_is_the_calibrated_non_uniform_pattern():
    """sensors.toml's waymo_top: the TOP LiDAR's 64 calibrated beams, not a uniform
    stand-in: about -17.6 .. +2.5 deg, ~0.6 deg apart at the bottom, ~0.16 deg near the horizon."""
    profile = get_profile("waymo_top")
    elevations = np.asarray(profile.elevations_deg)
    assert profile.beams == 64 and profile.points_per_beam == 2650
    assert elevations[0] == pytest.approx(-17.5468) and elevations[-1] == pytest.approx(2.5028)
    spacing = np.diff(elevations)
    assert (spacing > 0).all()
    assert spacing[:4].min() > 0.5 and spacing[-16:].max() < 0.2  # denser near the horizon
    assert profile.mount_height_m == pytest.approx(2.184)


def test_synth_scans_exactly_the_waymo_top_beams(tmp_path):
    from dali_cli.store.artifacts import FrameSet

    out = tmp_path / "w"
    result = CliRunner().invoke(
        main, ["synth", "--sensor", "waymo_top", "--frames", "1", "--seed", "3", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    xyz = FrameSet(out).frame(0)[:, :3].astype(np.float64)
    elevation = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    beams = np.asarray(get_profile("waymo_top").elevations_deg)
    nearest = np.abs(elevation[:, None] - beams[None]).min(axis=1)
    assert len(xyz) > 10_000 and nearest.max() < 0.01  # every point on a calibrated beam
    # beams below the horizon all reach the ground somewhere in a 360 degree scene
    hit_beams = np.unique(np.abs(elevation[:, None] - beams[None]).argmin(axis=1))
    assert set(np.flatnonzero(beams < -1.0)) <= set(hit_beams)
