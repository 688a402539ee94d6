"""Scan registration (dali_cli.registration): poses of scans of a known street recovered from
the scans alone, the constant-velocity prior, the voxel map's nearest-neighbour search, and
the errors of sequences it cannot register."""

from __future__ import annotations

import numpy as np
import pytest
from street_scans import scan, step_errors, trajectory

from dali_cli.registration import (
    RegistrationError,
    RegistrationParams,
    add_to_map,
    index_map,
    nearest_in_map,
    register_scans,
    voxel_downsample,
    voxel_keys,
)


def registered(truth: np.ndarray, **params):
    scans = [scan(pose, seed=i) for i, pose in enumerate(truth)]
    return register_scans(len(scans), lambda i: scans[i], RegistrationParams(**params))


@pytest.fixture(scope="module")
def street_drive():
    truth = trajectory(np.full(14, 1.2))  # 12 m/s at 10 Hz, turning 0.6 degrees a scan
    return truth, registered(truth)


def test_the_poses_of_a_drive_are_recovered_from_its_scans(street_drive):
    truth, result = street_drive
    np.testing.assert_allclose(result.poses[0], np.eye(4))
    translation, rotation = step_errors(result.poses, truth)
    assert translation.max() < 0.05 and rotation.max() < 0.2, (translation, rotation)
    path = np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1).sum()
    drift = np.linalg.norm(result.poses[-1, :3, 3] - truth[-1, :3, 3])
    assert drift < 0.01 * path, drift
    assert result.converged[1:].all() and (result.iterations[1:] > 0).all()
    assert (result.points > 500).all()


def test_registration_is_deterministic(street_drive):
    truth, result = street_drive
    again = registered(truth[:4])
    np.testing.assert_array_equal(again.poses, result.poses[:4])
    np.testing.assert_array_equal(again.iterations, result.iterations[:4])


def test_the_constant_velocity_prior_follows_a_car_speeding_up():
    """From 5 to 30 m/s: each scan starts where the last step puts it (off by 0.5 m, the
    speed-up); without the prior it starts up to 3 m off, beyond the map search's reach."""
    truth = trajectory(np.array([0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.0]))
    with_prior = registered(truth)
    translation, rotation = step_errors(with_prior.poses, truth)
    assert translation.max() < 0.05 and rotation.max() < 0.2, (translation, rotation)
    without = registered(truth, motion_prior=False)
    translation, _ = step_errors(without.poses, truth)
    assert translation.max() > 1.0, translation


def test_the_map_search_finds_the_nearest_point_within_a_voxel(tmp_path):
    rng = np.random.default_rng(1)
    points = rng.uniform(-5, 5, (3000, 3))
    index = index_map(points, 1.0)
    queries = rng.uniform(-6, 6, (500, 3))
    nearest, distance2 = nearest_in_map(index, queries)
    brute = ((queries[:, None, :] - points[None, :, :]) ** 2).sum(axis=2)  # (500, 3000)
    close = brute.min(axis=1) <= 1.0  # within a voxel edge: always among the 27 voxels
    assert close.sum() > 300
    np.testing.assert_allclose(distance2[close], brute.min(axis=1)[close])
    found = index.points[nearest[close]]
    np.testing.assert_array_equal(found, points[brute[close].argmin(axis=1)])
    assert (distance2[nearest < 0] == np.inf).all() and (distance2[nearest >= 0] < 4 * 3).all()


def test_voxels_keep_one_point_when_thinned_and_a_capped_number_in_the_map():
    points = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [1.5, 0.1, 0.1], [-0.1, 0.1, 0.1]])
    np.testing.assert_array_equal(voxel_downsample(points, 1.0), points[[0, 2, 3]])
    grid = np.full((30, 3), 0.5) + np.linspace(0, 0.4, 30)[:, None]  # 30 points, one voxel
    kept = add_to_map(grid[:10], grid[10:], 1.0, max_per_voxel=20)
    np.testing.assert_array_equal(kept, grid[:20])  # the map's own points first
    with pytest.raises(ValueError, match="voxels"):
        voxel_keys(np.array([[1e7, 0.0, 0.0]]), 1.0)


def test_sequences_it_cannot_register_are_errors_naming_the_scan():
    good = scan(trajectory(np.zeros(1))[0])
    with pytest.raises(RegistrationError, match="1 scan"):
        register_scans(1, lambda i: good)
    bad = good.copy()
    bad[7, 1] = np.nan
    with pytest.raises(RegistrationError, match="scan 1: points are NaN/inf") as error:
        register_scans(3, lambda i: bad if i == 1 else good)
    assert error.value.scan == 1
    near = good[np.linalg.norm(good[:, :3], axis=1) < 4]  # the ego's surroundings only
    with pytest.raises(RegistrationError, match=r"scan 2: \d+ points within 3-80 m") as error:
        register_scans(3, lambda i: near if i == 2 else good)
    assert error.value.scan == 2
