"""One box per parked car fitted to all of its registered points (`dali track-pseudo
--fit-track-points`): the car's points of every scan of its drive, moved into the world frame by
the scans' poses, accumulated in the frame of the car's tracked box, and the box's extents along
and across its heading (and its top) set from them. Target points only, no label.

Why: a detector's boxes of a car barely vary in size (the shipped KITTI model's lengths span
3.8-4.0 m where KITTI's cars span 3.2-5.0 m), and the tracked box is their median. One scan
sees a few faces of a car sparsely; the scans of a whole pass see them densely.

A LiDAR sees a car's near faces only, so a side of the box is set from the points only where
that side is bounded by them. A face is seen when the points within `face_depth_m` of the
extent's end, of the scans whose sensor stood beyond that face's plane (the only scans that can
see it), span at least `face_share` of the box's other side (its width for an end face, its
length for a side or the roof): the points near a car's front seen from behind are its side's
and roof's edges, not its front. An end (along the heading) is bounded when its face was seen; a
side (across the heading) when its face was seen or an end face was (an end face spans the car's
width); the top when the roof was seen. Where a side is not
bounded, the detector's size stays as a prior: the box keeps the detector's length from the one
seen end (or the points' extent, when longer); with neither end seen, the detector's box is
shifted just enough to hold the points. The bottom is never seen (the ground is removed): it
stays the detector's. The width and lateral place stay the detector's unless `across` (TrackFit).

Candidate points of a car in a scan are those in its box grown by `margin_along_m` /
`margin_across_m`, at least `ground_clearance_m` above its bottom and at most 0.3 m above its
top, and not within 0.15 m of a box of the scan that outranks the car: a moving car's, or a
parked car's scored higher (a low-scored box on the front half of a long car, the detector's
fragment of it, takes none of its points; two cars side by side keep their own). Along and across the
heading, points beyond an empty stretch of `gap_m` from the box (a car parked just behind, a
hedge beside) are dropped; the extents are the `quantile` and 1 - `quantile` quantiles.

Plain numpy. Boxes are `(N, 7)` float64 `x, y, z, l, w, h, yaw` (dali_cli.geometry); a pose is
`(4, 4)` float64, a scan's LiDAR frame in the world frame. Lengths in metres.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from dali_cli.geometry import point_box_pairs, points_in_box_frames

TOP_MARGIN_M = 0.3  # candidate points may reach this far above the box (its height is a guess)
CLAIM_MARGIN_M = 0.15  # a point this close to another box belongs to that car
FACE_MIN_POINTS = 5  # a face is seen only with at least this many points on it


@dataclass(frozen=True)
class TrackFit:
    """The fit's parameters (the module docstring); `min_points`: a car with fewer accumulated
    candidate points keeps its tracked box; `across`: fit the width and the lateral position
    too (off: on drive 0001 the accumulated near side lies ~5 cm beyond the true one, the far
    side, seen only at an end face's rounded corner, short of it, and the detector's width and
    lateral place, already fitted to the points scan by scan, scored better)."""

    margin_along_m: float = 1.0
    margin_across_m: float = 0.5
    ground_clearance_m: float = 0.4
    quantile: float = 0.01
    gap_m: float = 0.4
    face_depth_m: float = 0.25
    face_share: float = 0.5
    min_points: int = 30
    across: bool = False

    def __post_init__(self):
        wrong = [
            name
            for name, ok in (
                ("margin_along_m", self.margin_along_m >= 0),
                ("margin_across_m", self.margin_across_m >= 0),
                ("ground_clearance_m", self.ground_clearance_m >= 0),
                ("quantile", 0 <= self.quantile < 0.5),
                ("gap_m", self.gap_m > 0),
                ("face_depth_m", self.face_depth_m > 0),
                ("face_share", 0 < self.face_share <= 1),
                ("min_points", self.min_points >= 1),
            )
            if not ok
        ]
        if wrong:
            raise ValueError(
                f"track fit: {', '.join(wrong)} out of range (margins and the clearance >= 0, "
                "0 <= quantile < 0.5, gap and face depth > 0, 0 < face_share <= 1, "
                "min_points >= 1)"
            )

    def record(self) -> dict:
        """The manifest's record of the fit (its every parameter)."""
        return asdict(self)


def claim_ranks(score: np.ndarray) -> np.ndarray:
    """`(K,)` int64 rank of each car by `score (K,)`, 0 the highest (ties: the lower index)."""
    rank = np.empty(len(score), np.int64)
    rank[np.lexsort((np.arange(len(score)), -np.asarray(score, np.float64)))] = np.arange(
        len(score)
    )
    return rank


def scan_points(
    cars: np.ndarray,
    score: np.ndarray,
    pose: np.ndarray,
    points: np.ndarray,
    others: np.ndarray,
    fit: TrackFit,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The candidate points of one scan for each car (the module docstring).

    cars : (K, 7) world boxes; score : (K,) their scores (a car's points are taken by a higher
    scored car's box); pose : (4, 4) the scan's LiDAR pose; points : (M, >=3) in its LiDAR
    frame; others : (J, 7) world boxes of the scan's other cars (moving ones), whose points are
    no parked car's. Returns car (n,) int64 index into `cars`, uvz (n, 3) float64
    the point in that car's box frame (u along its heading, v to its left, z up from its
    bottom) and sensor (n, 3) float64 the scan's sensor (its LiDAR origin) in the same frame."""
    cars = np.asarray(cars, np.float64).reshape(-1, 7)
    if not len(cars) or not len(points):
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3))
    xyz = np.asarray(points[:, :3], np.float64) @ pose[:3, :3].T + pose[:3, 3]  # (M, 3) world
    grown = max(fit.margin_along_m, fit.margin_across_m)
    point, car = point_box_pairs(xyz, cars, grown)  # (P,) pairs, a superset
    frame = points_in_box_frames(xyz[point], cars[car])  # (P, 3) u, v, z from the centre
    half = cars[car, 3:6] / 2  # (P, 3)
    keep = np.abs(frame[:, 0]) <= half[:, 0] + fit.margin_along_m
    keep &= np.abs(frame[:, 1]) <= half[:, 1] + fit.margin_across_m
    keep &= frame[:, 2] >= -half[:, 2] + fit.ground_clearance_m
    keep &= frame[:, 2] <= half[:, 2] + TOP_MARGIN_M
    others = np.asarray(others, np.float64).reshape(-1, 7)
    rank = np.r_[claim_ranks(score), np.full(len(others), -1)]  # (K + J,): moving cars first
    claim_point, claim_box = point_box_pairs(xyz, np.concatenate([cars, others]), CLAIM_MARGIN_M)
    top = np.full(len(xyz), len(cars), np.int64)  # (M,) the best rank claiming each point
    np.minimum.at(top, claim_point, rank[claim_box])
    keep &= top[point] >= rank[car]  # no box outranking the car claims the point
    bottom = np.c_[np.zeros((keep.sum(), 2)), half[keep, 2]]  # (n, 3): z from the box's bottom
    sensor = points_in_box_frames(np.broadcast_to(pose[:3, 3], (len(cars), 3)), cars)  # (K, 3)
    return car[keep], frame[keep] + bottom, sensor[car[keep]] + bottom


def accumulate(
    cars: np.ndarray,
    score: np.ndarray,
    poses: np.ndarray,
    points_of: Callable[[int], np.ndarray],
    others_of: Callable[[int], np.ndarray],
    fit: TrackFit,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """scan_points over every scan `f` of a drive (cars (K, 7) and their score (K,), poses
    (F, 4, 4), points_of(f) -> (M, >=3),
    others_of(f) -> (J, 7) world boxes), concatenated: car (n,) int64, uvz (n, 3) and sensor
    (n, 3) float64."""
    parts = [
        scan_points(cars, score, poses[f], points_of(f), others_of(f), fit)
        for f in range(len(poses))
    ]
    if not parts:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3))
    return tuple(np.concatenate(column) for column in zip(*parts, strict=True))


def connected(values: np.ndarray, low: float, high: float, gap_m: float) -> np.ndarray:
    """`(n,)` bool: the values (n,) joined to the interval [low, high] by no empty stretch longer
    than `gap_m` (values inside it are joined)."""
    order = np.argsort(values, kind="stable")
    ordered = values[order]
    run = np.r_[0, np.cumsum(np.diff(ordered) > gap_m)]  # (n,) run id of each sorted value
    near = (ordered >= low - gap_m) & (ordered <= high + gap_m)
    joined = np.zeros(run[-1] + 1 if len(run) else 0, bool)
    joined[run[near]] = True
    out = np.zeros(len(values), bool)
    out[order] = joined[run]
    return out


def face_seen(
    along: np.ndarray,
    across: np.ndarray,
    sensor: np.ndarray,
    end: float,
    sign: int,
    span_m: float,
    fit: TrackFit,
) -> bool:
    """Is the face at `end` of the `along` axis (its high end for sign +1, low end for -1) seen:
    at least FACE_MIN_POINTS points within face_depth_m of it from scans whose sensor stood
    beyond it, spanning (the 5-95 % range of their `across` coordinates) at least `span_m`?
    along, across : (n,) the points' coordinates; sensor : (n,) their scan's sensor's `along`."""
    on_face = across[(sign * (end - along) <= fit.face_depth_m) & (sign * (sensor - end) > 0)]
    if len(on_face) < FACE_MIN_POINTS:
        return False
    low, high = np.quantile(on_face, [0.05, 0.95])
    return bool(high - low >= span_m)


def bounded_interval(
    low: float, high: float, seen_low: bool, seen_high: bool, prior_low: float, prior_high: float
) -> tuple[float, float]:
    """The box's interval on one axis from its points' extent [low, high] and which of its ends
    are bounded by points; the prior interval (the detector's) [prior_low, prior_high] gives the
    size where an end is not: from a seen end the prior size (or the extent, when longer); with
    no end seen, the prior interval shifted just enough to hold the extent (or the extent)."""
    size = prior_high - prior_low
    if seen_low and seen_high:
        return low, high
    if seen_low:
        return low, max(high, low + size)
    if seen_high:
        return min(low, high - size), high
    if high - low >= size:
        return low, high
    start = min(max(prior_low, high - size), low)
    return start, start + size


def fit_car(box: np.ndarray, uvz: np.ndarray, sensor: np.ndarray, fit: TrackFit) -> np.ndarray:
    """`(7,)` one car's tracked world box `box (7,)` fitted to its accumulated candidate points
    `uvz (n, 3)` (its box frame, z from its bottom) seen from `sensor (n, 3)` (each point's
    scan's sensor, same frame; scan_points): heading kept, centre and l, w, h set where the
    points bound them (the module docstring); too few points: `box` as it is."""
    box = np.asarray(box, np.float64)
    length, width, height = box[3:6]
    if len(uvz) < fit.min_points:
        return box.copy()
    inside = connected(uvz[:, 0], -length / 2, length / 2, fit.gap_m)
    inside &= connected(uvz[:, 1], -width / 2, width / 2, fit.gap_m)
    (u, v, z), (su, sv, sz) = uvz[inside].T, sensor[inside].T
    if len(u) < fit.min_points:
        return box.copy()
    quantiles = [fit.quantile, 1 - fit.quantile]
    (u_low, u_high), (v_low, v_high) = np.quantile(u, quantiles), np.quantile(v, quantiles)
    top = float(np.quantile(z, 1 - fit.quantile))
    across, along = fit.face_share * width, fit.face_share * length
    ends = [face_seen(u, v, su, end, sign, across, fit) for end, sign in ((u_low, -1), (u_high, 1))]
    sides = [face_seen(v, u, sv, end, sign, along, fit) for end, sign in ((v_low, -1), (v_high, 1))]
    roof = face_seen(z, u, sz, top, 1, along, fit)
    u_low, u_high = bounded_interval(u_low, u_high, *ends, -length / 2, length / 2)
    any_end = ends[0] or ends[1]
    v_low, v_high = (
        bounded_interval(
            v_low, v_high, sides[0] or any_end, sides[1] or any_end, -width / 2, width / 2
        )
        if fit.across
        else (-width / 2, width / 2)
    )
    _, top = bounded_interval(0.0, top, True, roof, 0.0, height)
    du, dv = (u_low + u_high) / 2, (v_low + v_high) / 2
    c, s = np.cos(box[6]), np.sin(box[6])
    return np.r_[
        box[0] + c * du - s * dv,
        box[1] + s * du + c * dv,
        box[2] - height / 2 + top / 2,
        u_high - u_low,
        v_high - v_low,
        top,
        box[6],
    ]


def fit_cars(
    cars: np.ndarray, car: np.ndarray, uvz: np.ndarray, sensor: np.ndarray, fit: TrackFit
) -> tuple[np.ndarray, np.ndarray]:
    """`(K, 7)` every car's box (cars (K, 7) world boxes) fitted to its points (car (n,) index,
    uvz (n, 3), sensor (n, 3); accumulate) by fit_car, and `(K,)` int64 the candidate points
    each had."""
    cars = np.asarray(cars, np.float64).reshape(-1, 7)
    order = np.argsort(car, kind="stable")
    bounds = np.searchsorted(car[order], np.arange(len(cars) + 1))
    rows = [order[bounds[k] : bounds[k + 1]] for k in range(len(cars))]
    fitted = [fit_car(cars[k], uvz[rows[k]], sensor[rows[k]], fit) for k in range(len(cars))]
    return np.array(fitted).reshape(-1, 7), np.diff(bounds).astype(np.int64)
