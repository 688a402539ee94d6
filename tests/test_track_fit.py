"""dali_cli.labels.track_fit: a parked car's box fitted to its points of every scan."""

from __future__ import annotations

import numpy as np
import pytest
from test_tracks import ego_poses

from dali_cli.geometry import inside_boxes
from dali_cli.labels import track_fit, tracks

FIT = track_fit.TrackFit(across=True)
# the true car: 4.6 m long, 1.85 m wide, 1.5 m high, its bottom on the ground (z = -1.73)
TRUTH = np.array([20.0, 5.0, -1.73 + 0.75, 4.6, 1.85, 1.5, 0.1])
# the detector's box of it: the usual 3.9 x 1.65 car, 0.3 m off along it, 0.1 m across, too low
PRIOR = TRUTH + np.array([0.3 * np.cos(0.1), 0.3 * np.sin(0.1), -0.05, -0.7, -0.2, -0.1, 0.0])


def visible_faces(box: np.ndarray, sensor: np.ndarray, rng, per_face: int = 120) -> np.ndarray:
    """`(n, 3)` world points on the faces of `box` `(7,)` that face the world point `sensor`
    `(3,)` (a LiDAR sees a car's near faces only; a box is convex, so these are all it sees),
    its bottom excluded, with 1 cm noise."""
    half = box[3:6] / 2
    c, s = np.cos(box[6]), np.sin(box[6])
    offset = sensor - box[:3]
    seen_from = np.array([c * offset[0] + s * offset[1], -s * offset[0] + c * offset[1], offset[2]])
    parts = []
    for axis, sign in ((0, 1), (0, -1), (1, 1), (1, -1), (2, 1)):
        if sign * seen_from[axis] <= half[axis]:
            continue  # the sensor is behind this face's plane
        local = rng.uniform(-1, 1, (per_face, 3)) * half
        local[:, axis] = sign * half[axis]
        parts.append(local)
    local = np.concatenate(parts) + rng.normal(0, 0.01, (sum(map(len, parts)), 3))
    xy = local[:, :2] @ np.array([[c, s], [-s, c]]) + box[:2]
    return np.c_[xy, local[:, 2] + box[2]]


def ground(centre: np.ndarray, rng, count: int = 400) -> np.ndarray:
    """`(count, 3)` ground points (z = -1.73 +- 3 cm) within 4 m of `centre` (x, y)."""
    xy = centre[:2] + rng.uniform(-4, 4, (count, 2))
    return np.c_[xy, rng.normal(-1.73, 0.03, count)]


def scans(cars: list[np.ndarray], poses: np.ndarray, seed: int = 0) -> list[np.ndarray]:
    """Per pose `(F, 4, 4)`, the `(n, 4)` LiDAR-frame points of the faces of the world boxes
    `cars` that face the sensor there, and of the ground around the first car."""
    rng = np.random.default_rng(seed)
    out = []
    for pose in poses:
        sensor = pose[:3, 3]
        world = np.concatenate(
            [visible_faces(b, sensor, rng) for b in cars] + [ground(cars[0], rng)]
        )
        inverse = np.linalg.inv(pose)
        local = world @ inverse[:3, :3].T + inverse[:3, 3]
        out.append(np.c_[local, np.full(len(local), 0.5)].astype(np.float32))
    return out


def fit_one(prior, poses, points, others=None, parked=None, fit=FIT):
    """The fitted box `(7,)` of one car (world box `prior`, scored 0.6) over the scans, and its
    points; `parked` `(J, 8)`: other parked cars' world boxes and scores; `others` `(J, 7)`:
    moving cars' boxes."""
    others = np.zeros((0, 7)) if others is None else others
    parked = np.zeros((0, 8)) if parked is None else parked
    cars, score = np.vstack([prior, parked[:, :7]]), np.r_[0.6, parked[:, 7]]
    car, uvz, sensor = track_fit.accumulate(
        cars, score, poses, points.__getitem__, lambda f: others, fit
    )
    boxes, used = track_fit.fit_cars(cars, car, uvz, sensor, fit)
    return boxes[0], used[0]


def straight(frames: int, start_x: float, step_m: float) -> np.ndarray:
    """`(frames, 4, 4)` LiDAR poses driving along the world x axis from x = `start_x`, `step_m`
    a scan (the LiDAR 1.73 m above the ground)."""
    poses = ego_poses(frames, step_m=step_m, turn_deg=0.0)
    poses[:, 0, 3] += start_x
    return poses


def test_a_car_passed_by_is_fitted_to_its_true_length_width_and_position():
    poses = straight(30, -5.0, 1.5)  # from 25 m behind the car to 20 m past it
    fitted, used = fit_one(PRIOR, poses, scans([TRUTH], poses))
    assert used > 1000
    np.testing.assert_allclose(fitted[3:5], TRUTH[3:5], atol=0.05)
    np.testing.assert_allclose(fitted[:2], TRUTH[:2], atol=0.05)
    assert fitted[6] == PRIOR[6]  # the heading stays the track's
    assert abs(fitted[5] - TRUTH[5]) < 0.1  # the roof is seen: the height is the points'


def test_an_end_never_seen_keeps_the_detectors_length_from_the_seen_end():
    # a short car seen only from behind and beside (the sensor never passes its front), its
    # detector's box longer than it: the points end short of the front, which is no face
    short = TRUTH.copy()
    short[3] = 3.5
    prior = short + np.array([0.2 * np.cos(0.1), 0.2 * np.sin(0.1), 0.0, 0.5, 0.0, 0.0, 0.0])
    poses = straight(12, -5.0, 1.2)  # sensor x from -5 to 8: the car's rear is at x ~ 18
    fitted, _ = fit_one(prior, poses, scans([short], poses))
    assert fitted[3] == pytest.approx(prior[3])  # the prior length, not the points' extent
    rear = lambda box: box[:2] - box[3] / 2 * np.array([np.cos(box[6]), np.sin(box[6])])  # noqa: E731
    np.testing.assert_allclose(rear(fitted), rear(short), atol=0.05)  # from the seen rear end


def test_a_long_car_seen_from_behind_grows_to_its_points_not_past_them():
    poses = straight(12, -5.0, 1.2)
    points = scans([TRUTH], poses)
    fitted, _ = fit_one(PRIOR, poses, points)
    # longer than the prior where the points reach; the far end no further than the points
    assert PRIOR[3] < fitted[3] <= TRUTH[3] + 0.05
    every = np.concatenate([p[:, :3] @ pose[:3, :3].T + pose[:3, 3] for p, pose in zip(points, poses, strict=True)])  # fmt: skip
    on_car = inside_boxes(every, TRUTH, margin_m=0.05) & (every[:, 2] > -1.73 + 0.3)
    assert inside_boxes(every[on_car], fitted, margin_m=0.05).mean() > 0.97


def test_a_car_parked_just_behind_and_never_detected_is_cut_off_by_the_gap():
    neighbour = TRUTH.copy()
    neighbour[:2] -= (TRUTH[3] + 0.5) * np.array([np.cos(0.1), np.sin(0.1)])  # 0.5 m behind
    centred = PRIOR.copy()
    centred[:2] = TRUTH[:2]  # its grown box reaches 0.65 m past the true rear: the neighbour's face
    poses = straight(30, -5.0, 1.5)
    fitted, _ = fit_one(centred, poses, scans([TRUTH, neighbour], poses))
    np.testing.assert_allclose(fitted[3], TRUTH[3], atol=0.05)


def test_another_cars_points_are_not_this_cars():
    # a moving car's box overlapping this one's margin claims its points
    neighbour = TRUTH.copy()
    neighbour[:2] -= (TRUTH[3] + 0.3) * np.array([np.cos(0.1), np.sin(0.1)])  # 0.3 m behind
    poses = straight(30, -5.0, 1.5)
    points = scans([TRUTH, neighbour], poses)
    fitted, _ = fit_one(PRIOR, poses, points, others=neighbour[None])
    np.testing.assert_allclose(fitted[3], TRUTH[3], atol=0.05)
    unclaimed, _ = fit_one(PRIOR, poses, points)
    assert unclaimed[3] > TRUTH[3] + 0.2  # without the claim, its front face joins this car


def test_a_lower_scored_box_on_the_cars_front_takes_none_of_its_points():
    # the detector's fragment of a long car: a box on its front half, scored lower
    fragment = TRUTH.copy()
    fragment[:2] += 1.2 * np.array([np.cos(0.1), np.sin(0.1)])
    fragment[3] = 3.0
    poses = straight(30, -5.0, 1.5)
    points = scans([TRUTH], poses)
    fitted, _ = fit_one(PRIOR, poses, points, parked=np.r_[fragment, 0.2][None])
    np.testing.assert_allclose(fitted[3], TRUTH[3], atol=0.05)
    # scored higher than the car, the same box does take them
    taken, _ = fit_one(PRIOR, poses, points, parked=np.r_[fragment, 0.9][None])
    assert taken[3] < TRUTH[3] - 0.5


def test_by_default_the_width_and_lateral_place_stay_the_detectors():
    poses = straight(30, -5.0, 1.5)
    fitted, _ = fit_one(PRIOR, poses, scans([TRUTH], poses), fit=track_fit.TrackFit())
    np.testing.assert_allclose(fitted[3], TRUTH[3], atol=0.05)  # the length is fitted
    assert fitted[4] == PRIOR[4]
    c, s = np.cos(PRIOR[6]), np.sin(PRIOR[6])
    across = -s * (fitted[0] - PRIOR[0]) + c * (fitted[1] - PRIOR[1])
    assert abs(across) < 1e-9


def test_no_points_one_scan_and_no_cars_keep_the_tracked_boxes():
    poses = straight(3, -5.0, 1.5)
    empty = [np.zeros((0, 4), np.float32)] * 3
    fitted, used = fit_one(PRIOR, poses, empty)
    assert used == 0
    np.testing.assert_array_equal(fitted, PRIOR)
    ground_only = [np.c_[ground(TRUTH, np.random.default_rng(1)), np.zeros(400)]] * 3
    fitted, _ = fit_one(PRIOR, poses, [np.asarray(g, np.float32) for g in ground_only])
    np.testing.assert_array_equal(fitted, PRIOR)  # the ground is no car
    one = straight(1, 14.0, 1.0)  # one scan from just behind the car's left rear
    fitted, used = fit_one(PRIOR, one, scans([TRUTH], one))
    assert used > FIT.min_points and np.isfinite(fitted).all()
    assert fitted[3] >= PRIOR[3] - 1e-9  # one face seen: the length is no shorter than the prior
    nothing = np.zeros((0, 3))
    cars, counts = track_fit.fit_cars(
        np.zeros((0, 7)), np.zeros(0, np.int64), nothing, nothing, FIT
    )
    assert cars.shape == (0, 7) and counts.shape == (0,)
    car, uvz, sensor = track_fit.scan_points(np.zeros((0, 7)), np.zeros(0), np.eye(4), np.ones((5, 3)), np.zeros((0, 7)), FIT)  # fmt: skip
    assert car.shape == (0,) and uvz.shape == (0, 3) and sensor.shape == (0, 3)


def test_track_boxes_places_the_fitted_box_and_without_the_fit_the_median_box():
    poses = straight(30, -5.0, 1.5)
    points = scans([TRUTH], poses)
    local = np.concatenate([tracks.boxes_from_world(PRIOR[None], pose) for pose in poses])
    args = (np.arange(30), local, np.full(30, 0.6), np.full(30, 100), poses, points.__getitem__)
    plain = tracks.track_boxes(*args)
    fitted = tracks.track_boxes(*args, fit=FIT)
    assert len(fitted.frame) == 30 and len(plain.frame) == 30
    np.testing.assert_allclose(plain.boxes[:, 3:5], PRIOR[3:5][None].repeat(30, 0), atol=1e-9)
    np.testing.assert_allclose(fitted.boxes[:, 3:5], TRUTH[3:5][None].repeat(30, 0), atol=0.05)
    # placed in each scan where the car is: back in the world frame, one box at the truth
    world = np.concatenate(
        [tracks.boxes_to_world(fitted.boxes[[i]], poses[f]) for i, f in enumerate(fitted.frame)]
    )
    np.testing.assert_allclose(world[:, :2], TRUTH[:2][None].repeat(30, 0), atol=0.05)


@pytest.mark.parametrize(
    "name, value", [("gap_m", 0.0), ("quantile", 0.5), ("face_share", 0.0), ("min_points", 0)]
)
def test_bad_fit_parameters_are_refused(name, value):
    with pytest.raises(ValueError):
        track_fit.TrackFit(**{name: value})
