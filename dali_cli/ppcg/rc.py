"""RC (ray-constrained) pseudo points of one frame: re-cast each in-box point's ray onto a fitted model.

For every box with `min_points <= car points < max_points` (frame.py defines car points) a model is
selected and fitted, the rays sensor -> car point are cast against it, and each car point moves to
its ray's first hit (CAD: first triangle; point model: nearest model point within theta_th, see
point_models). The point keeps its intensity and its ray. Misses and hits below the box's ground
height are dropped (METHOD: misses are dropped); a box left with fewer than `min_points` hits keeps
its raw points and is recorded as `no_hits`. Dense boxes are skipped. RC never adds points.
With `orient`, a box whose model fits its points better turned round is turned round first
(dali_cli.ppcg.orient; the boxes RC processes only: dense and sparse ones keep their heading).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dali_cli.geometry import shrink_boxes
from dali_cli.ppcg.fitting import box_rng
from dali_cli.ppcg.frame import RC, BoxRecords, PpcgParams, assemble, car_points, ground_heights
from dali_cli.ppcg.models import ModelBank
from dali_cli.ppcg.orient import flips, turned


@dataclass(frozen=True, kw_only=True)
class RcParams(PpcgParams):
    """RC settings: the shared ones (frame.PpcgParams), the sensor's mount height (m) and the
    boxes processed, those with min_points <= points < max_points."""

    mount_height_m: float
    max_points: int = 300
    min_points: int = 3


def rc_frame(
    frame_id: str, points: np.ndarray, boxes: np.ndarray, bank: ModelBank, params: RcParams
) -> tuple[np.ndarray, BoxRecords]:
    """RC of one frame: points `(n, 4)` float32 and its boxes `(k, 7)` -> new points `(n', 4)`
    float32 (n' <= n) and the per-box records. Deterministic in (params.seed, frame_id, box order)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    ground_z = ground_heights(boxes, params.mount_height_m, params.ground_margin_m)
    members, ground = car_points(points, boxes, ground_z, params.point_margin_m)
    before = np.array([len(m) for m in members], dtype=np.int32)
    records = BoxRecords.raw(before, ground)
    records.reason[before < params.min_points] = "too_few_points"
    records.reason[before >= params.max_points] = "dense"
    eligible = np.flatnonzero((before >= params.min_points) & (before < params.max_points))
    if len(eligible) == 0:
        return points, records
    rngs = [box_rng(params.seed, frame_id, int(i)) for i in eligible] if params.top_k > 1 else None
    bodies = shrink_boxes(boxes, params.label_slack_m)  # (k, 7) what the models fill
    models = bank.select(bodies[eligible], params.top_k, rngs)
    if params.orient:  # mesh selection is by size: the same model either way round
        flip = flips(bank, models, bodies[eligible], points, [members[i] for i in eligible])
        records.flipped[eligible] = flip
        bodies = turned(bodies, records.flipped)
    index = [members[i] for i in eligible]
    bounds = np.r_[0, np.cumsum([len(m) for m in index])]  # (B + 1,) rays of each box
    index = np.concatenate(index)  # (N,) the car points of all eligible boxes
    hit, xyz = bank.cast_many(models, bodies[eligible], points[index, :3], bounds, params.theta_rad)
    keep = hit.copy()
    box_of_ray = np.repeat(eligible, np.diff(bounds))
    keep[hit] = xyz[hit, 2] >= ground_z[box_of_ray[hit]]
    kept = np.add.reduceat(keep.astype(np.int64), bounds[:-1])  # (B,) segments are never empty
    enough = kept >= params.min_points  # (B,)
    records.reason[eligible[~enough]] = "no_hits"
    done = eligible[enough]
    records.ppcg[done] = RC
    records.points_after[done] = kept[enough]
    records.model_id[done] = np.asarray(bank.model_ids, dtype=object)[models[enough]]
    used = np.repeat(enough, np.diff(bounds))  # (N,) rays of boxes that get their RC points
    replace, remove = used & keep, used & ~keep
    removed, replaced = [index[remove]], [(index[replace], xyz[replace])]
    new = assemble(points, removed, replaced, [])
    return new, records
