"""dali_cli.labels.tracks: boxes in a world frame, tracks over scans, parked cars."""

from __future__ import annotations

import numpy as np
import pytest

from dali_cli.geometry import bev_iou, wrap_angle
from dali_cli.labels import tracks

PARAMS = tracks.TrackParams()


def ego_poses(frames: int, step_m: float = 1.2, turn_deg: float = 1.0) -> np.ndarray:
    """`(frames, 4, 4)` LiDAR poses of a car driving forward `step_m` a scan, turning left
    `turn_deg` a scan (the first pose the identity)."""
    poses = np.tile(np.eye(4), (frames, 1, 1))
    heading, position = 0.0, np.zeros(2)
    for i in range(frames):
        c, s = np.cos(heading), np.sin(heading)
        poses[i, :2, :2] = [[c, -s], [s, c]]
        poses[i, :2, 3] = position
        position = position + step_m * np.array([c, s])
        heading += np.radians(turn_deg)
    return poses


def seen_from(world_box: np.ndarray, poses: np.ndarray, jitter_m: float, seed: int = 0):
    """One box per scan: `world_box` `(7,)` in each scan's LiDAR frame, its centre jittered."""
    rng = np.random.default_rng(seed)
    local = np.concatenate([tracks.boxes_from_world(world_box[None], pose) for pose in poses])
    local[:, :2] += rng.normal(0.0, jitter_m, (len(poses), 2))
    return local


def link_scans(per_scan_boxes: list[np.ndarray], per_scan_scores: list[np.ndarray], poses):
    """frame, world boxes, scores and track ids of boxes given per scan (LiDAR frames)."""
    frame = np.concatenate([np.full(len(b), i) for i, b in enumerate(per_scan_boxes)])
    world = np.concatenate(
        [tracks.boxes_to_world(b, poses[i]) for i, b in enumerate(per_scan_boxes)]
    ).reshape(-1, 7)
    score = np.concatenate(per_scan_scores)
    return frame, world, score, tracks.link_tracks(frame, world, score, PARAMS)


def test_world_frame_round_trip_keeps_boxes():
    rng = np.random.default_rng(1)
    poses = ego_poses(5, step_m=3.0, turn_deg=20.0)
    boxes = np.c_[rng.uniform(-40, 40, (6, 3)), rng.uniform(1, 5, (6, 3)), rng.uniform(-3, 3, 6)]
    for pose in poses:
        back = tracks.boxes_from_world(tracks.boxes_to_world(boxes, pose), pose)
        np.testing.assert_allclose(back[:, :6], boxes[:, :6], atol=1e-9)
        np.testing.assert_allclose(wrap_angle(back[:, 6] - boxes[:, 6]), 0.0, atol=1e-9)


def test_a_parked_car_under_ego_motion_is_one_track_and_one_car():
    poses = ego_poses(12)
    car = np.array([25.0, 6.0, -0.8, 4.2, 1.8, 1.5, 0.3])
    seen = seen_from(car, poses, jitter_m=0.15)
    # in its own scan the car is 25 m ahead at first and 12 m behind the start at the end: a
    # LiDAR-frame track would see it move 14 m; the world frame sees it stand still
    assert seen[0, 0] - seen[-1, 0] > 10.0
    frame, world, score, track = link_scans(
        [b[None] for b in seen], [np.array([0.5])] * len(seen), poses
    )
    assert len(np.unique(track)) == 1
    assert tracks.track_lengths(track).min() == len(seen)
    car_of, boxes, scores = tracks.parked_cars(track, frame, world, score, PARAMS)
    assert (car_of == 0).all() and len(boxes) == 1
    assert np.linalg.norm(boxes[0, :2] - car[:2]) < 0.15
    assert scores[0] == pytest.approx(0.5)


def test_a_one_scan_clutter_box_is_no_car():
    poses = ego_poses(8)
    car = seen_from(np.array([20.0, -5.0, -0.8, 4.0, 1.7, 1.5, 0.0]), poses, jitter_m=0.1)
    per_scan = [car[i][None] for i in range(len(poses))]
    scores = [np.array([0.6]) for _ in poses]
    clutter = np.array([[15.0, 8.0, -0.8, 3.9, 1.6, 1.5, 1.0]])
    per_scan[4] = np.vstack([per_scan[4], clutter])
    scores[4] = np.array([0.6, 0.9])  # scored above the car: the score alone would keep it
    frame, world, score, track = link_scans(per_scan, scores, poses)
    clutter_row = np.flatnonzero((frame == 4) & (score == 0.9))[0]
    assert tracks.track_lengths(track)[clutter_row] == 1
    car_of, boxes, _ = tracks.parked_cars(track, frame, world, score, PARAMS)
    assert car_of[clutter_row] == -1
    assert len(boxes) == 1


def test_a_moving_car_is_one_track_across_a_missed_scan_and_not_parked():
    poses = ego_poses(10, step_m=1.0, turn_deg=0.0)
    # the car drives at 15 m/s (1.5 m a scan at 10 Hz) across the ego's path; missed in scan 5,
    # it is 3 m from its last box in scan 6, found where its velocity puts it
    world_boxes = np.array(
        [[30.0, -10.0 + 1.5 * i, -0.8, 4, 1.7, 1.5, np.pi / 2] for i in range(10)]
    )
    local = [tracks.boxes_from_world(world_boxes[[i]], poses[i]) for i in range(10)]
    local[5] = np.zeros((0, 7))
    scores = [np.full(len(b), 0.5) for b in local]
    frame, world, score, track = link_scans(local, scores, poses)
    assert len(np.unique(track)) == 1
    car_of, boxes, _ = tracks.parked_cars(track, frame, world, score, PARAMS)
    assert (car_of == -1).all() and len(boxes) == 0


def test_parked_fragments_merge_and_the_heading_follows_the_majority():
    poses = ego_poses(12)
    car = np.array([25.0, 6.0, -0.8, 4.2, 1.8, 1.5, 0.3])
    seen = seen_from(car, poses, jitter_m=0.1)
    seen[[2, 5], 6] += np.pi  # two boxes turned round: the same axis
    per_scan = [b[None] for b in seen]
    per_scan[6] = np.zeros((0, 7))  # a gap longer than max_gap splits the track ...
    per_scan[7] = np.zeros((0, 7))
    per_scan[8] = np.zeros((0, 7))
    scores = [np.full(len(b), 0.5) for b in per_scan]
    frame, world, score, track = link_scans(per_scan, scores, poses)
    assert len(np.unique(track)) == 2
    car_of, boxes, _ = tracks.parked_cars(track, frame, world, score, PARAMS)
    assert len(boxes) == 1 and (car_of == 0).all()  # ... and the car joins them again
    assert abs(wrap_angle(boxes[0, 6] - car[6])) < np.radians(2)


def test_place_in_scan_needs_points_in_the_box():
    pose = ego_poses(3)[2]
    parked = np.array([[25.0, 6.0, -0.8, 4.2, 1.8, 1.5, 0.3], [40.0, -6.0, -0.8, 4.0, 1.7, 1.5, 0]])
    local = tracks.boxes_from_world(parked, pose)
    rng = np.random.default_rng(0)
    points = local[0, :3] + rng.uniform(-0.5, 0.5, (12, 3))  # only the first car has points
    index, boxes, counts = tracks.place_in_scan(parked, pose, points, min_points=5)
    assert index.tolist() == [0] and counts.tolist() == [12]
    assert bev_iou(boxes, local[:1])[0, 0] == pytest.approx(1.0)


def test_fill_gaps_puts_the_skipped_scan_between_its_neighbours():
    track = np.array([0, 0])
    frame = np.array([3, 5])
    world = np.array([[10.0, 0, 0, 4, 2, 1.5, 0.2], [12.0, 2, 0, 4, 2, 1.5, -0.2]])
    new_track, new_frame, new_world = tracks.fill_gaps(track, frame, world)
    assert new_track.tolist() == [0] and new_frame.tolist() == [4]
    np.testing.assert_allclose(new_world[0], [11.0, 1, 0, 4, 2, 1.5, 0.0], atol=1e-12)


def test_tracked_boxes_face_their_cars_way_on_a_drive_where_half_face_the_sensor():
    """A synthetic drive: four parked cars, two facing the ego's way and two facing the sensor,
    whose boxes point the wrong way in a third of the scans (at lower scores), and two moving
    cars, one ahead in the ego's lane and one oncoming, whose boxes' fronts are a coin flip.
    After track_boxes every parked car faces the score-weighted vote of its boxes and every
    moving box faces where its car goes."""
    frames = 12
    poses = ego_poses(frames, step_m=1.0, turn_deg=0.0)
    rng = np.random.default_rng(4)
    parked = np.array([[20.0, 5.0, -0.8, 4.2, 1.8, 1.5, 0.0], [28.0, 5.0, -0.8, 4.2, 1.8, 1.5, 0.0],
                       [22.0, -5.0, -0.8, 4.2, 1.8, 1.5, np.pi],
                       [30.0, -5.0, -0.8, 4.2, 1.8, 1.5, np.pi]])  # fmt: skip
    moving = [(np.array([15.0, 0.0]), 1.5), (np.array([60.0, -2.5]), -1.5)]  # start, m a scan
    boxes, scores, truth_yaw = [], [], []
    for f in range(frames):
        world = [b.copy() for b in parked]
        for start, step in moving:
            world.append(
                np.r_[start + [step * f, 0.0], -0.8, 4.3, 1.8, 1.5, 0.0 if step > 0 else np.pi]
            )
        world = np.array(world)
        seen = tracks.boxes_from_world(world, poses[f])
        score = np.full(len(seen), 0.8)
        wrong = np.zeros(len(seen), bool)
        wrong[:4] = rng.random(4) < 1 / 3  # parked: a third turned round, less sure
        wrong[4:] = rng.random(2) < 0.5  # moving: a coin flip
        seen[wrong, 6] = wrap_angle(seen[wrong, 6] + np.pi)
        score[wrong & (np.arange(len(seen)) < 4)] = 0.55
        boxes.append(seen)
        scores.append(score)
        truth_yaw.append(world[:, 6])
    frame = np.concatenate([np.full(len(b), i) for i, b in enumerate(boxes)])
    points = [np.zeros((0, 3)) for _ in range(frames)]
    # the parked cars' placed boxes need points: one per car corner region, in each scan's frame
    for f in range(frames):
        local = tracks.boxes_from_world(parked, poses[f])
        points[f] = np.repeat(local[:, :3], 10, axis=0) + rng.normal(0, 0.2, (40, 3))
    result = tracks.track_boxes(
        frame, np.concatenate(boxes), np.concatenate(scores),
        np.full(len(frame), 50), poses, lambda f: points[f], PARAMS,
    )  # fmt: skip
    assert result.parked.sum() >= 4 * (frames - 2) and (~result.parked).sum() >= 2 * (frames - 3)
    for row in range(len(result.frame)):
        f = result.frame[row]
        world = tracks.boxes_to_world(result.boxes[[row]], poses[f])[0]
        truth = np.array([b for b in [*parked]] + [np.r_[s + [st * f, 0.0], -0.8, 4.3, 1.8, 1.5,
                          0.0 if st > 0 else np.pi] for s, st in moving])  # fmt: skip
        nearest = np.argmin(np.hypot(*(truth[:, :2] - world[:2]).T))
        assert np.cos(world[6] - truth[nearest, 6]) > 0, (row, result.parked[row])
