"""How far a car's surface sits inside its labelled box: constructed faces at known depths."""

from __future__ import annotations

import numpy as np
import pytest

from dali_cli.reporting import domains
from dali_cli.reporting.surface_inset import MIN_POINTS, surface_insets


def _car_surface(box, end_inset: float, side_inset: float, rng, count: int = 400) -> np.ndarray:
    """Points `(2 * count, 3)` on the rear end face and right side face of `box` `(7,)`, `end_inset`
    and `side_inset` metres inside them (box frame → sensor frame by the box's yaw)."""
    x, y, z, length, width, height, yaw = box
    up = rng.uniform(-0.2 * height, 0.45 * height, 2 * count)
    end = np.c_[
        np.full(count, -(length / 2 - end_inset)) + rng.normal(0, 0.01, count),
        rng.uniform(-width / 2 + 0.4, width / 2 - 0.4, count),
    ]
    side = np.c_[
        rng.uniform(-length / 2 + 0.7, length / 2 - 0.7, count),
        np.full(count, -(width / 2 - side_inset)) + rng.normal(0, 0.01, count),
    ]
    local = np.concatenate([end, side])
    cos, sin = np.cos(yaw), np.sin(yaw)
    world = np.c_[
        cos * local[:, 0] - sin * local[:, 1] + x, sin * local[:, 0] + cos * local[:, 1] + y
    ]
    return np.c_[world, z + up]


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.5])
def test_insets_of_faces_at_known_depths_in_any_heading(yaw):
    rng = np.random.default_rng(0)
    # the sensor at the origin sees the box's rear (-x local) and right (-y local) faces
    local_centre = np.array([7.0, 4.0])
    cos, sin = np.cos(yaw), np.sin(yaw)
    centre = [
        cos * local_centre[0] - sin * local_centre[1],
        sin * local_centre[0] + cos * local_centre[1],
    ]
    box = np.array([*centre, -0.9, 4.2, 1.8, 1.5, yaw])
    points = _car_surface(box, 0.14, 0.07, rng)
    insets = surface_insets(points, box[None])
    np.testing.assert_allclose(insets, [[0.14, 0.07]], atol=0.01)
    # a surface that fills its box, and one that pokes out of it
    np.testing.assert_allclose(surface_insets(_car_surface(box, 0.0, -0.05, rng), box[None]),
                               [[0.0, -0.05]], atol=0.01)  # fmt: skip


def test_unseen_faces_and_sparse_cars_have_no_inset():
    rng = np.random.default_rng(1)
    # the sensor sits beside the car, level with its end faces: only the side face is seen
    box = np.array([0.3, 6.0, -0.9, 4.2, 1.8, 1.5, 0.0])
    local = _car_surface(np.array([0.0, 0.0, 0.0, 4.2, 1.8, 1.5, 0.0]), 0.1, 0.05, rng)
    points = local + box[:3]
    insets = surface_insets(points, box[None])
    assert np.isnan(insets[0, 0]) and insets[0, 1] == pytest.approx(0.05, abs=0.01)
    sparse = surface_insets(points[: MIN_POINTS - 1], box[None])
    assert np.isnan(sparse).all()
    assert surface_insets(np.zeros((0, 4)), np.zeros((0, 7))).shape == (0, 2)


def test_domain_statistics_report_the_median_insets():
    rng = np.random.default_rng(2)
    boxes = np.array([[8.0, -3.0, -0.9, 4.2, 1.8, 1.5, 0.0], [12.0, 3.0, -0.9, 4.0, 1.7, 1.5, 0.0]])
    loose = [_car_surface(boxes[0], 0.15, 0.08, rng), _car_surface(boxes[1], 0.13, 0.06, rng)]
    frame = np.c_[np.concatenate(loose), np.full(sum(map(len, loose)), 0.3)]
    stats = domains.summarize([domains.frame_stats(frame, boxes, 360.0, rng)]).values
    assert stats["end_face_inset_m"] == pytest.approx(0.14, abs=0.01)
    # the first car turns its left side to the sensor, but its points lie on its right
    assert stats["cars_end_face"] == 2 and stats["cars_side_face"] == 1
    assert stats["side_face_inset_m"] == pytest.approx(0.06, abs=0.01)
    table = domains.format_table([("loose", stats)])
    assert "end face" in table and " / 2" in table
    empty = domains.summarize([domains.frame_stats(frame, np.zeros((0, 7)), 360.0, rng)]).values
    assert empty["end_face_inset_m"] is None and empty["cars_end_face"] == 0
