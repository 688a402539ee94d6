"""Beam removal (dali_cli.importers.beams, `dali import kitti|kitti-raw|kitti-odometry --beams`):
the k-means beam assignment recovers the rings of a synthetic HDL-64E scan, the thinning keeps
the beams and points the protocol names, and an import at 16 / 32 beams records the thinned
sensor profile that the later stages read."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st
from test_kitti_odometry import write_dataset

from dali_cli.cli import main
from dali_cli.importers.beams import azimuths_rad, beam_labels, cluster_1d, keep_mask
from dali_cli.ppcg.run import target_profile
from dali_cli.sensors import get_profile, spherical_directions
from dali_cli.store.artifacts import FrameSet, read_boxes

FIXTURES = Path(__file__).resolve().parent / "fixtures"
KITTI = FIXTURES / "real" / "kitti"
SCAN = KITTI / "training" / "velodyne" / "000008.bin"
DRIVE = FIXTURES / "kitti_raw" / "2011_09_26" / "2011_09_26_drive_0001_sync"


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def synthetic_scan(profile_name: str, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A noise-free scan of the profile's rays: (points `(n, 4)` float32, ring `(n,)` of each
    point, 0 = the lowest beam). Returns thin out as in a real street scan: beams above the
    horizon keep a fifth of their rays (sky), the lowest ones half (the car's own body)."""
    profile = get_profile(profile_name)
    rng = np.random.default_rng(seed)
    elevation, azimuth = profile.elevations_rad(), profile.azimuths_rad()  # (B,), (P,)
    ring, column = np.meshgrid(np.arange(profile.beams), np.arange(len(azimuth)), indexing="ij")
    ring, column = ring.ravel(), column.ravel()  # (B * P,)
    returned = np.where(elevation[ring] > 0, 0.2, np.where(elevation[ring] < -0.35, 0.5, 0.94))
    hit = rng.random(len(ring)) < returned
    ring, column = ring[hit], column[hit]
    directions = spherical_directions(elevation[ring], azimuth[column])  # (n, 3)
    distance = rng.uniform(2.0, 80.0, len(ring))[:, None]
    points = np.c_[directions * distance, rng.random(len(ring))].astype(np.float32)
    order = rng.permutation(len(ring))  # no help from the scan order
    return points[order], ring[order]


@pytest.mark.parametrize("profile", ["kitti", "kitti_hdl64e"])
def test_beams_of_a_synthetic_hdl64e_scan_are_recovered(profile):
    """Both layouts: evenly spaced, and the sheet's two blocks (1/3 and 1/2 degree apart)."""
    points, ring = synthetic_scan(profile)
    labels = beam_labels(points)
    assert np.mean(labels == ring) >= 0.99


@pytest.mark.parametrize("beams", [32, 16])
def test_the_kept_beams_are_every_nth_from_the_lowest(beams):
    points, ring = synthetic_scan("kitti_hdl64e", seed=1)
    keep = keep_mask(points, beams)
    step = 64 // beams
    kept_rings = np.unique(ring[keep])
    assert set(kept_rings) == set(range(0, 64, step))  # beam 0, the lowest, is kept; 63 is not
    assert np.array_equal(keep, ring % step == 0)


def test_azimuth_halving_keeps_every_second_point_of_each_kept_beam():
    points, ring = synthetic_scan("kitti", seed=2)
    keep = keep_mask(points, 16, azimuth_half=True)
    full = keep_mask(points, 16)
    assert not (keep & ~full).any()
    azimuth = azimuths_rad(points)
    for beam in range(0, 64, 4):
        members = np.flatnonzero(ring == beam)
        in_order = members[np.argsort(azimuth[members])]
        expected = np.arange(len(in_order)) % 2 == 0
        assert np.array_equal(keep[in_order], expected), beam


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.integers(-3000, 1000).map(lambda hundredths: hundredths / 100), max_size=300),
    st.integers(1, 70),
)
def test_cluster_1d_is_a_converged_sorted_clustering(values, clusters):
    """Elevations in hundredths of a degree, as many distinct values as clusters or fewer."""
    values = np.asarray(values + [0.0])
    labels, centres = cluster_1d(values, clusters)
    assert labels.shape == values.shape and centres.shape == (clusters,)
    assert np.all(np.diff(centres) >= 0)
    # sorted values get non-decreasing labels (each cluster a run) ...
    order = np.argsort(values, kind="stable")
    assert np.all(np.diff(labels[order]) >= 0)
    # ... and every value is at its own centre or as close to another (Lloyd converged)
    own = np.abs(values - centres[labels])
    nearest = np.abs(values[:, None] - centres[None, :]).min(axis=1)
    assert np.allclose(own, nearest, atol=1e-9)
    distinct = len(np.unique(values))
    assert len(np.unique(labels)) == min(distinct, clusters)


def test_real_scan_keeps_about_a_half_and_a_quarter():
    """KITTI frame 000008 (camera-field cloud): every beam crosses the image."""
    points = np.fromfile(SCAN, np.float32).reshape(-1, 4)
    assert 0.45 <= keep_mask(points, 32).mean() <= 0.55
    assert 0.2 <= keep_mask(points, 16).mean() <= 0.3
    assert 0.1 <= keep_mask(points, 16, azimuth_half=True).mean() <= 0.15


def test_thinned_profiles_are_the_kitti_profile_s_kept_beams():
    kitti = get_profile("kitti")
    for beams in (32, 16):
        for half in ("", "-half"):
            thinned = get_profile(f"kitti-{beams}{half}")
            kept = np.asarray(kitti.elevations_deg)[:: 64 // beams]
            assert np.allclose(thinned.elevations_deg, kept, atol=1e-4)
            per_beam = math.ceil(kitti.points_per_beam / 2) if half else kitti.points_per_beam
            assert thinned.points_per_beam == per_beam
            for key in ("mount_height_m", "max_range_m", "min_range_m", "car_mean_lwh_m"):
                assert getattr(thinned, key) == getattr(kitti, key), key


def manifest(out: Path) -> dict:
    return json.loads((out / "manifest.json").read_text())


def test_import_kitti_at_16_beams_records_the_thinned_sensor(tmp_path):
    out = tmp_path / "k16"
    result = invoke("import", "kitti", KITTI, "--beams", "16", "--out", out, "--no-progress")
    assert result.exit_code == 0, result.output
    frames = FrameSet(out)
    assert frames.sensor == "kitti-16"
    params = manifest(out)["params"]
    assert params["beams"] == 16 and params["beams_azimuth_half"] is False
    assert params["sensor"] == "kitti-16"
    points = np.fromfile(SCAN, np.float32).reshape(-1, 4)
    assert frames.num_points == int(keep_mask(points, 16).sum())
    # the boxes count the kept points only
    full = tmp_path / "k64"
    assert invoke("import", "kitti", KITTI, "--out", full, "--no-progress").exit_code == 0
    assert "beams" not in manifest(full)["params"]  # the default leaves the manifest as it was
    sparse, dense = read_boxes(out)["num_points"], read_boxes(full)["num_points"]
    assert (sparse <= dense).all() and sparse.sum() < 0.4 * dense.sum()
    # the later stages read the sparse sensor: PPCG's rays (RC and CF), PTSN's profile
    name, profile = target_profile(frames, None, None)
    assert name == "kitti-16" and profile.beams == 16
    assert len(profile.ray_pattern().directions) == 16 * profile.points_per_beam


def test_import_kitti_raw_and_odometry_at_32_beams(tmp_path):
    raw = tmp_path / "raw"
    flags = ["--beams", "32", "--beams-azimuth-half", "--no-progress"]
    result = invoke("import", "kitti-raw", DRIVE, "--crop-fov", *flags, "--out", raw)
    assert result.exit_code == 0, result.output
    assert FrameSet(raw).sensor == "kitti-32-half"
    assert manifest(raw)["params"]["beams_azimuth_half"] is True
    sequence = write_dataset(tmp_path / "dataset")
    odometry = tmp_path / "odometry"
    result = invoke("import", "kitti-odometry", sequence, "--beams", "32", "--out", odometry)
    assert result.exit_code == 0, result.output
    assert FrameSet(odometry).sensor == "kitti-32"
    assert manifest(odometry)["params"]["beams"] == 32


def test_bad_beam_options_are_usage_errors_and_write_nothing(tmp_path):
    out = tmp_path / "out"
    result = invoke("import", "kitti", KITTI, "--beams", "8", "--out", out)
    assert result.exit_code == 2 and "--beams" in result.output
    result = invoke("import", "kitti", KITTI, "--beams-azimuth-half", "--out", out)
    assert result.exit_code == 2 and "--beams-azimuth-half" in result.output
    assert not out.exists()
    # a sensors.toml without the thinned profile names it
    sensors = tmp_path / "sensors.toml"
    text = (Path(__file__).resolve().parent.parent / "sensors.toml").read_text()
    sensors.write_text(text.split("\n# KITTI thinned")[0])
    result = invoke("import", "kitti", KITTI, "--beams", "16", "--sensors", sensors, "--out", out)
    assert result.exit_code != 0 and "kitti-16" in result.output
    assert not out.exists()
