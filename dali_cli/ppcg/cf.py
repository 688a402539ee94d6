"""CF (constraint-free) pseudo points of one frame: scan each fitted model afresh at a far range.

Every box is moved radially (along the sensor -> box direction in BEV, heading and height kept) so
its centre lies at a range drawn per box from `range_m`; the target sensor's rays inside the moved
box's angular window are cast against the fitted model; the first hits inside the sensor's range
limits are moved back by the same translation and replace the box's car points (frame.py). A box
with no hits keeps its raw points (`no_hits`). CF points get the median intensity of the box's raw
car points (the profile's car intensity when it has none). Occlusion between objects is ignored.
With `orient`, a box whose model fits its points better turned round is turned round first
(dali_cli.ppcg.orient).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dali_cli.geometry import shrink_boxes
from dali_cli.ppcg.fitting import box_rng, box_uniform
from dali_cli.ppcg.frame import CF, BoxRecords, PpcgParams, assemble, car_points, ground_heights
from dali_cli.ppcg.models import ModelBank
from dali_cli.ppcg.orient import flips, turned
from dali_cli.ppcg.window import box_windows, windows_directions
from dali_cli.sensors import SensorProfile


@dataclass(frozen=True, kw_only=True)
class CfParams(PpcgParams):
    """CF settings: the shared ones (frame.PpcgParams) and range_m, the (low, high) centre
    range in metres."""

    range_m: tuple[float, float] = (20.0, 50.0)


def move_radially(boxes: np.ndarray, ranges_m: np.ndarray) -> np.ndarray:
    """Boxes `(k, 7)` translated along their BEV direction so the centre lies at `ranges_m` `(k,)`.

    Returns the translations `(k, 3)` (z = 0); a box at the origin moves along +x.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    distance = np.hypot(boxes[:, 0], boxes[:, 1])
    safe = np.maximum(distance, 1e-9)
    unit = np.where((distance > 1e-9)[:, None], boxes[:, :2] / safe[:, None], [1.0, 0.0])
    shift = unit * (np.asarray(ranges_m, dtype=np.float64) - distance)[:, None]
    return np.concatenate([shift, np.zeros((len(boxes), 1))], axis=1)


def median(values: np.ndarray) -> np.floating:
    """np.median of a non-empty 1-D array without NaN, with the same result bits (the mean of
    the two middle values is their sum in the array's dtype, halved), at a fraction of its
    per-call cost."""
    count = len(values)
    middle = count // 2
    if count % 2:
        return np.partition(values, middle)[middle]
    low, high = np.partition(values, (middle - 1, middle))[middle - 1 : middle + 1]
    return (low + high) / 2


def cf_frame(
    frame_id: str,
    points: np.ndarray,
    boxes: np.ndarray,
    bank: ModelBank,
    profile: SensorProfile,
    params: CfParams,
) -> tuple[np.ndarray, BoxRecords]:
    """CF of one frame: points `(n, 4)` float32, boxes `(k, 7)` -> new points `(n', 4)` float32
    and per-box records. Deterministic in (params.seed, frame_id, box order)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    if len(boxes) == 0:
        return points, BoxRecords.raw(np.zeros(0, np.int32))
    ground_z = ground_heights(boxes, profile.mount_height_m, params.ground_margin_m)
    members, ground = car_points(points, boxes, ground_z, params.point_margin_m)
    before = np.array([len(m) for m in members], dtype=np.int32)
    records = BoxRecords.raw(before, ground)
    low, high = params.range_m
    ranges = low + (high - low) * np.array(
        [box_uniform(params.seed, frame_id, i, "cf-range") for i in range(len(boxes))]
    )
    rngs = None
    if params.top_k > 1:
        rngs = [box_rng(params.seed, frame_id, i) for i in range(len(boxes))]
    bodies = shrink_boxes(boxes, params.label_slack_m)  # (k, 7) what the models fill
    models = bank.select(bodies, params.top_k, rngs)
    if params.orient:  # mesh selection is by size: the same model either way round
        records.flipped[:] = flips(bank, models, bodies, points, members)
        bodies = turned(bodies, records.flipped)
    shift = move_radially(boxes, ranges)  # (k, 3)
    moved = boxes.copy()
    moved[:, :3] += shift
    bodies[:, :3] += shift
    windows = box_windows(moved)
    directions, bounds = windows_directions(profile, windows)  # only each window's rays
    hit, xyz = bank.cast_many(models, bodies, directions, bounds, params.theta_rad)
    box_of_ray = np.repeat(np.arange(len(boxes)), np.diff(bounds))  # (N,)
    distance = np.linalg.norm(np.where(hit[:, None], xyz, 0.0), axis=1)
    hit &= (distance >= profile.min_range_m) & (distance <= profile.max_range_m)
    xyz = xyz[hit] - shift[box_of_ray[hit]]  # moved back
    box_of_ray = box_of_ray[hit]
    above = xyz[:, 2] >= ground_z[box_of_ray]
    xyz, box_of_ray = xyz[above], box_of_ray[above]  # grouped by box, in box order
    counts = np.bincount(box_of_ray, minlength=len(boxes))  # (k,)
    records.reason[counts == 0] = "no_hits"
    done = np.flatnonzero(counts > 0)
    intensity = np.array(
        [
            median(points[members[i], 3]) if len(members[i]) else profile.intensity_car
            for i in range(len(boxes))
        ]
    )
    records.ppcg[done] = CF
    records.points_after[done] = counts[done]
    records.model_id[done] = np.asarray(bank.model_ids, dtype=object)[models[done]]
    added = np.concatenate([xyz, intensity[box_of_ray, None]], axis=1)
    removed = [members[i] for i in done]
    return assemble(points, removed, [], [added]), records
