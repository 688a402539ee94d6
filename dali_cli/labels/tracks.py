"""Pseudo boxes over a scan sequence: boxes moved into one world frame by the scans' poses,
linked into tracks scan by scan, parked cars made one box each and placed in every scan that
holds them (the scans the detector missed them in included), and what does not persist dropped.
Which way a tracked car faces comes from the track: a moving car faces the way it moves (boxes
aligned along their track, as Autoware's tracker and LISO do), a parked car the way the
score-weighted vote of its boxes' directions says (the detector's direction head).

Plain numpy. Boxes are `(N, 7)` float64 `x, y, z, l, w, h, yaw` (dali_cli.geometry); a pose is
`(4, 4)` float64, a scan's LiDAR frame in the world frame (x_world = pose @ x_lidar).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dali_cli.geometry import count_points_in_boxes, wrap_angle

# a tracked car is kept when its score (a parked car's median, a moving track's mean) is at least
# this: on drive 2011_09_26_drive_0001 the true cars' lie at 0.50-0.55, clutter's mostly < 0.45
# (docs/RESULTS.md, "Pseudo labels that persist over a drive"); set by the detector's score scale
TRACK_SCORE_MIN = 0.5


@dataclass(frozen=True)
class TrackParams:
    """gate_m: a box joins a track when its BEV centre is within this many metres of where the
    track is predicted to be (constant velocity in the world frame), and parked tracks this close
    are one car; max_gap: frames a track may go unseen before it ends; parked_m_per_frame: a
    track whose world centre moved less than this per frame of its span (3 m/s at 10 Hz) is a
    parked car: its boxes sliding with the visible part of the car are not motion; min_hits: a
    car (parked or moving) must be found in this many scans, or it is clutter; min_points: a
    parked car's box is placed in a scan only when it holds this many of the scan's points."""

    gate_m: float = 2.0
    max_gap: int = 2
    parked_m_per_frame: float = 0.3
    min_hits: int = 3
    min_points: int = 5


def yaw_of(pose: np.ndarray) -> np.ndarray:
    """`(...)` heading (rad) of the x axis of `(..., 4, 4)` poses, about the world z."""
    return np.arctan2(pose[..., 1, 0], pose[..., 0, 0])


def boxes_to_world(boxes: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """`(N, 7)` boxes of one scan -> the world frame of `pose` `(4, 4)` (yaw turned by the
    pose's heading; roll and pitch of a driving car are left out of the box's yaw)."""
    out = boxes.astype(np.float64, copy=True)
    out[:, :3] = boxes[:, :3] @ pose[:3, :3].T + pose[:3, 3]
    out[:, 6] = wrap_angle(boxes[:, 6] + yaw_of(pose))
    return out


def boxes_from_world(boxes: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """`(N, 7)` world boxes -> the LiDAR frame of the scan at `pose` (boxes_to_world's inverse)."""
    inverse = np.linalg.inv(pose)
    out = boxes.astype(np.float64, copy=True)
    out[:, :3] = boxes[:, :3] @ inverse[:3, :3].T + inverse[:3, 3]
    out[:, 6] = wrap_angle(boxes[:, 6] - yaw_of(pose))
    return out


def link_tracks(
    frame: np.ndarray, world: np.ndarray, score: np.ndarray, params: TrackParams = TrackParams()
) -> np.ndarray:
    """`(N,)` int64 track id of every box: frame by frame, boxes by descending score, each box
    joins the nearest live track (BEV centre within `gate_m` of the track's predicted centre, one
    box per track and frame) or starts a new one.

    frame : (N,) int frame position in the sequence (0, 1, ...); world : (N, 7) boxes in the
    world frame; score : (N,) float.
    """
    track = np.full(len(frame), -1, np.int64)
    last_xy = np.zeros((0, 2))  # (T, 2) world centre at the last hit
    velocity = np.zeros((0, 2))  # (T, 2) metres per frame
    last_frame = np.zeros(0, np.int64)  # (T,)
    for t in np.unique(frame):
        rows = np.flatnonzero(frame == t)
        rows = rows[np.argsort(-score[rows], kind="stable")]
        gap = t - last_frame  # (T,)
        live = gap <= params.max_gap + 1
        predicted = last_xy + velocity * gap[:, None]  # (T, 2)
        taken = ~live
        for row in rows:
            distance = np.linalg.norm(predicted - world[row, :2], axis=1)  # (T,)
            distance[taken] = np.inf
            best = int(np.argmin(distance)) if len(distance) else -1
            if best >= 0 and distance[best] <= params.gate_m:
                velocity[best] = (world[row, :2] - last_xy[best]) / gap[best]
                last_xy[best], last_frame[best] = world[row, :2], t
                taken[best] = True
                track[row] = best
            else:
                track[row] = len(last_xy)
                last_xy = np.vstack([last_xy, world[row, :2]])
                velocity = np.vstack([velocity, np.zeros(2)])
                last_frame = np.append(last_frame, t)
                taken = np.append(taken, True)
                predicted = np.vstack([predicted, world[row, :2]])
    return track


def track_lengths(track: np.ndarray) -> np.ndarray:
    """`(N,)` per box: the number of frames its track was seen in (its hits)."""
    _, inverse, counts = np.unique(track, return_inverse=True, return_counts=True)
    return counts[inverse]


def track_mean(track: np.ndarray, values: np.ndarray) -> np.ndarray:
    """`(N,)` per box: the mean of `values` `(N,)` over its track."""
    ids, inverse = np.unique(track, return_inverse=True)
    sums = np.bincount(inverse, weights=values, minlength=len(ids))
    return (sums / np.bincount(inverse, minlength=len(ids)))[inverse]


def heading_axis(yaw: np.ndarray) -> float:
    """The mean heading axis (rad, modulo pi) of `(n,)` yaws: the mean of the doubled angles,
    so a box turned by pi counts as the same axis."""
    return 0.5 * float(np.arctan2(np.sin(2 * yaw).mean(), np.cos(2 * yaw).mean()))


def is_parked(span: int, world: np.ndarray, params: TrackParams) -> bool:
    """A track of `(n, 7)` world boxes (first to last, `span` frames apart) is parked when its
    centre moved less than parked_m_per_frame per frame of the span."""
    moved = float(np.linalg.norm(world[-1, :2] - world[0, :2]))
    return moved < params.parked_m_per_frame * max(span, 1)


def refine_tracks(
    track: np.ndarray,
    frame: np.ndarray,
    world: np.ndarray,
    size: bool = True,
    static: bool = True,
    params: TrackParams = TrackParams(),
) -> np.ndarray:
    """`(N, 7)` world boxes made consistent over their track: `size`: every box of a track takes
    the track's median l, w, h; `static`: a parked track's boxes (is_parked) take its median
    centre and its mean heading axis (each box keeps the direction along that axis nearest its
    own yaw). track, frame : (N,) int; world : (N, 7)."""
    out = world.copy()
    for t in np.unique(track):
        rows = np.flatnonzero(track == t)
        rows = rows[np.argsort(frame[rows], kind="stable")]
        if len(rows) < 2:
            continue
        if size:
            out[rows, 3:6] = np.median(world[rows, 3:6], axis=0)
        span = int(frame[rows[-1]] - frame[rows[0]])
        if static and is_parked(span, world[rows], params):
            out[rows, :3] = np.median(world[rows, :3], axis=0)
            axis = heading_axis(world[rows, 6])
            flip = np.abs(wrap_angle(world[rows, 6] - axis)) > np.pi / 2
            out[rows, 6] = wrap_angle(axis + np.pi * flip)
    return out


def fill_gaps(
    track: np.ndarray, frame: np.ndarray, world: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes for the frames a track skipped between two of its hits, linearly interpolated in
    the world frame (yaw along the shorter turn). Returns (track (M,), frame (M,), world (M, 7))
    of the new boxes only."""
    new_track, new_frame, new_world = [], [], []
    for t in np.unique(track):
        rows = np.flatnonzero(track == t)
        rows = rows[np.argsort(frame[rows], kind="stable")]
        for a, b in zip(rows[:-1], rows[1:], strict=True):
            for f in range(int(frame[a]) + 1, int(frame[b])):
                share = (f - frame[a]) / (frame[b] - frame[a])
                box = world[a] + share * (world[b] - world[a])
                box[6] = world[a, 6] + share * wrap_angle(world[b, 6] - world[a, 6])
                new_track.append(t)
                new_frame.append(f)
                new_world.append(box)
    return (
        np.asarray(new_track, np.int64),
        np.asarray(new_frame, np.int64),
        np.asarray(new_world, np.float64).reshape(-1, 7),
    )


def voted_direction(axis: float, yaw: np.ndarray, score: np.ndarray) -> float:
    """The end of heading `axis` (rad) that boxes with headings `yaw (n,)` vote for, each with
    its `score (n,)`: axis, or axis + pi when more score points the other way (a tie: axis)."""
    against = np.abs(wrap_angle(yaw - axis)) > np.pi / 2
    return float(wrap_angle(axis + np.pi * (score[against].sum() > score[~against].sum())))


def median_box(world: np.ndarray, score: np.ndarray) -> np.ndarray:
    """`(7,)` one box of the `(n, 7)` world boxes of one car: of its boxes scored at least their
    median score (the scans that saw the car best), the median centre and size and the mean
    heading axis, pointed the way the score-weighted vote of all its boxes says. score : (n,)."""
    best = world[score >= np.median(score)]
    axis = heading_axis(best[:, 6])
    return np.r_[np.median(best[:, :6], axis=0), voted_direction(axis, world[:, 6], score)]


def motion_headings(
    track: np.ndarray, frame: np.ndarray, world: np.ndarray, params: TrackParams = TrackParams()
) -> np.ndarray:
    """`(N,)` the direction (rad, world frame) each box's track moves in at its frame: the
    centre's change between the neighbouring hits (np.gradient over the frames); where the car
    moves less than parked_m_per_frame there, the direction from the track's first to its last
    centre; NaN for a track of one box or one that moved less than that over its span."""
    out = np.full(len(track), np.nan)
    for t in np.unique(track):
        rows = np.flatnonzero(track == t)
        rows = rows[np.argsort(frame[rows], kind="stable")]
        times = frame[rows].astype(np.float64)
        if len(rows) < 2 or times[-1] == times[0]:
            continue
        overall = world[rows[-1], :2] - world[rows[0], :2]
        if np.hypot(*overall) < params.parked_m_per_frame * (times[-1] - times[0]):
            continue
        velocity = np.stack([np.gradient(world[rows, k], times) for k in (0, 1)], axis=1)
        slow = np.hypot(velocity[:, 0], velocity[:, 1]) < params.parked_m_per_frame
        velocity[slow] = overall
        out[rows] = np.arctan2(velocity[:, 1], velocity[:, 0])
    return out


def along_motion(yaw: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """Headings `yaw (N,)` turned by pi where they point more than 90 deg away from `motion (N,)`
    (rad; NaN: kept as they are): the box's axis kept, its front where the car is going."""
    against = np.abs(wrap_angle(yaw - np.nan_to_num(motion))) > np.pi / 2
    return np.where(np.isnan(motion) | ~against, yaw, wrap_angle(yaw + np.pi))


def parked_cars(
    track: np.ndarray,
    frame: np.ndarray,
    world: np.ndarray,
    score: np.ndarray,
    params: TrackParams = TrackParams(),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parked cars of a linked sequence: parked tracks (is_parked) whose median centres lie
    within gate_m of each other merged (longest first) into one car each; cars found in fewer
    than min_hits scans dropped.

    Returns car : (N,) int64 per box (-1: in a moving track or a dropped car), boxes : (K, 7)
    world box per car (median_box of its boxes), score : (K,) the median score of its boxes."""
    car = np.full(len(track), -1, np.int64)
    ids, counts = np.unique(track, return_counts=True)
    centres: list[np.ndarray] = []
    for t in ids[np.argsort(-counts, kind="stable")]:
        rows = np.flatnonzero(track == t)
        rows = rows[np.argsort(frame[rows], kind="stable")]
        if not is_parked(int(frame[rows[-1]] - frame[rows[0]]), world[rows], params):
            continue
        centre = np.median(world[rows, :2], axis=0)
        distance = [np.linalg.norm(centre - other) for other in centres]
        if distance and min(distance) <= params.gate_m:
            car[rows] = int(np.argmin(distance))
        else:
            car[rows] = len(centres)
            centres.append(centre)
    kept = [k for k in range(len(centres)) if len(np.unique(frame[car == k])) >= params.min_hits]
    renumber = np.full(len(centres) + 1, -1, np.int64)  # index -1: the last slot, stays -1
    renumber[kept] = np.arange(len(kept))
    car = renumber[car]
    boxes = [median_box(world[car == k], score[car == k]) for k in range(len(kept))]
    boxes = np.array(boxes).reshape(-1, 7)
    scores = np.array([np.median(score[car == k]) for k in range(len(kept))], np.float64)
    return car, boxes, scores


def place_in_scan(
    boxes: np.ndarray, pose: np.ndarray, points: np.ndarray, min_points: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parked cars' world boxes `(K, 7)` in one scan (LiDAR `pose` `(4, 4)`, `points` `(M, >=3)`
    in its frame): the cars holding at least `min_points` of its points. Returns (index (k,) into
    `boxes`, local boxes (k, 7), point counts (k,))."""
    local = boxes_from_world(boxes, pose)
    counts = count_points_in_boxes(points, local) if len(local) else np.zeros(0, np.int64)
    index = np.flatnonzero(counts >= min_points)
    return index, local[index], counts[index]


def parked_tracks(track: np.ndarray, frame: np.ndarray, world: np.ndarray, params: TrackParams):
    """`(N,)` bool per box: its track is parked (is_parked)."""
    out = np.zeros(len(track), bool)
    for t in np.unique(track):
        rows = np.flatnonzero(track == t)
        rows = rows[np.argsort(frame[rows], kind="stable")]
        out[rows] = is_parked(int(frame[rows[-1]] - frame[rows[0]]), world[rows], params)
    return out


@dataclass
class TrackedBoxes:
    """The boxes of a sequence after tracking (M rows): frame (M,) int position of the scan;
    boxes (M, 7) in the scan's LiDAR frame; score (M,) the car's median or the moving track's
    mean score; num_points (M,) points of the scan in the box; car (M,) int64 id of the car
    (parked cars 0..K-1, then the moving tracks); parked (M,) bool; source_row (M,) int64 the
    input box a moving row is (-1 for a placed parked car)."""

    frame: np.ndarray
    boxes: np.ndarray
    score: np.ndarray
    num_points: np.ndarray
    car: np.ndarray
    parked: np.ndarray
    source_row: np.ndarray


def track_boxes(
    frame: np.ndarray,
    boxes: np.ndarray,
    score: np.ndarray,
    num_points: np.ndarray,
    poses: np.ndarray,
    points_of,
    params: TrackParams = TrackParams(),
    recording: list[str] | np.ndarray | None = None,
) -> TrackedBoxes:
    """Pseudo boxes of a sequence turned into tracked boxes: linked in the world frame
    (link_tracks); each parked car (parked_cars, found in >= min_hits scans) as one world box
    placed in every scan where it holds >= min_points points (place_in_scan), facing the way its
    boxes' score-weighted vote says; the boxes of moving tracks with >= min_hits hits as they
    are, each turned to face the way its track moves (motion_headings); every other box (clutter
    that does not persist) dropped.

    frame : (N,) int scan position (0..F-1); boxes : (N, 7) LiDAR frames; score : (N,);
    num_points : (N,) the points in each input box; poses : (F, 4, 4) LiDAR poses;
    points_of : callable(f) -> (M, >=3) points of scan f; recording : (F,) the recording
    (drive) of each scan, each tracked on its own (None: one recording).
    """
    if recording is not None:
        args = (frame, boxes, score, num_points, poses, points_of, params)
        return _track_recordings(np.asarray(recording, dtype=object), *args)
    world = np.empty_like(boxes, dtype=np.float64)
    for f in np.unique(frame):
        world[frame == f] = boxes_to_world(boxes[frame == f], poses[f])
    track = link_tracks(frame, world, score, params)
    car, car_boxes, car_scores = parked_cars(track, frame, world, score, params)
    moving = (car < 0) & (track_lengths(track) >= params.min_hits)
    moving &= ~parked_tracks(track, frame, world, params)
    parts = []
    for f in range(len(poses)):
        index, local, counts = place_in_scan(car_boxes, poses[f], points_of(f), params.min_points)
        parts.append((np.full(len(index), f), local, car_scores[index], counts, index))
    moving_rows = np.flatnonzero(moving)
    _, moving_id = np.unique(track[moving_rows], return_inverse=True)
    motion = motion_headings(track, frame, world, params)[moving_rows]
    moving_boxes = boxes[moving_rows].astype(np.float64, copy=True)
    aligned = along_motion(world[moving_rows, 6], motion)
    moving_boxes[:, 6] = wrap_angle(moving_boxes[:, 6] + (aligned - world[moving_rows, 6]))
    mean_score = track_mean(track, score)
    placed = [np.concatenate(column) for column in zip(*parts, strict=True)] if parts else None
    placed_frame, placed_boxes, placed_score, placed_points, placed_car = placed or [
        np.zeros(0, np.int64), np.zeros((0, 7)), np.zeros(0), np.zeros(0, np.int64),
        np.zeros(0, np.int64),
    ]  # fmt: skip
    return TrackedBoxes(
        frame=np.concatenate([placed_frame, frame[moving_rows]]).astype(np.int64),
        boxes=np.concatenate([placed_boxes.reshape(-1, 7), moving_boxes]),
        score=np.concatenate([placed_score, mean_score[moving_rows]]),
        num_points=np.concatenate([placed_points, num_points[moving_rows]]).astype(np.int64),
        car=np.concatenate([placed_car, len(car_boxes) + moving_id]).astype(np.int64),
        parked=np.r_[np.ones(len(placed_frame), bool), np.zeros(len(moving_rows), bool)],
        source_row=np.r_[np.full(len(placed_frame), -1), moving_rows].astype(np.int64),
    )


def _track_recordings(recording, frame, boxes, score, num_points, poses, points_of, params):
    """track_boxes on each recording (drive) of a set on its own: `recording` (F,) names the
    recording of each scan; scans of different recordings (poses in different world frames)
    are never linked, nor is a parked car placed in another recording's scans. Each
    recording's scans keep their order in the set. Returns the rows of every recording, frame
    positions (0..F-1), car ids (unique over the set) and source rows of the whole input."""
    parts, offset = [], 0
    for name in dict.fromkeys(recording.tolist()):
        positions = np.flatnonzero(recording == name)  # (Fr,) ascending
        rows = np.flatnonzero(np.isin(frame, positions))
        tracked = track_boxes(
            np.searchsorted(positions, frame[rows]), boxes[rows], score[rows], num_points[rows],
            poses[positions], lambda f, positions=positions: points_of(int(positions[f])), params,
        )  # fmt: skip
        moving = tracked.source_row >= 0
        tracked.frame = positions[tracked.frame]
        tracked.car = tracked.car + offset
        tracked.source_row = np.where(moving, rows[np.where(moving, tracked.source_row, 0)], -1)
        offset = int(tracked.car.max()) + 1 if len(tracked.car) else offset
        parts.append(tracked)
    fields = ("frame", "boxes", "score", "num_points", "car", "parked", "source_row")
    if not parts:
        return track_boxes(frame, boxes, score, num_points, poses, points_of, params)
    return TrackedBoxes(
        **{name: np.concatenate([getattr(part, name) for part in parts]) for name in fields}
    )
