"""What RC and CF share per frame: the ground rule for points in a box, and per-box records.

Ground rule: a box's points below `ground_z = max(box bottom, -mount height) + ground_margin_m`
(sensor frame) belong to the ground. They stay as they are and are not counted as the car's
points; generated points below that height are dropped. So a pseudo box that sinks into the road
punches no hole in it, and no generated point ends up under the road.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dali_cli.ppcg.inbox import points_per_box
from dali_cli.world.cars import LABEL_SLACK_M

# the stages' point margin (ppcg-rc/ppcg-cf --point-margin-m): 42 % of the true cars' points lay
# outside their pseudo boxes (demo scale, docs/ppcg.md)
DEFAULT_POINT_MARGIN_M = 0.3

# ppcg column values and reasons recorded per box
RC, CF, RAW = "rc", "cf", "raw"
REASONS = ("ok", "dense", "too_few_points", "no_hits")


@dataclass(frozen=True, kw_only=True)
class PpcgParams:
    """What RC and CF settings share. theta_rad: point-model angular threshold
    (point_models.angular_threshold_rad); top_k, seed: a box's model drawn among the K best by a
    per-box seed; ground_margin_m: the ground rule's margin (module doc); orient: turn boxes
    whose model fits better the other way round (mesh models only; None: with mesh models,
    decided by the stage, run.resolve_orient); point_margin_m: a box's points are those in the
    box grown by this (car_points); label_slack_m: (l, w, h) room the boxes leave around their
    cars, as the source's labels do (the model fills the box shrunk by it,
    geometry.shrink_boxes; the synthetic world's default)."""

    theta_rad: float
    top_k: int = 1
    seed: int = 0
    ground_margin_m: float = 0.1
    orient: bool | None = False
    point_margin_m: float = 0.0
    label_slack_m: tuple[float, float, float] = tuple(LABEL_SLACK_M)


def ground_heights(boxes: np.ndarray, mount_height_m: float, ground_margin_m: float) -> np.ndarray:
    """Per-box height `(k,)` (sensor frame, m) below which points count as ground (module doc)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    bottom = boxes[:, 2] - 0.5 * boxes[:, 5]
    return np.maximum(bottom, -float(mount_height_m)) + float(ground_margin_m)


def car_points(
    points: np.ndarray, boxes: np.ndarray, ground_z: np.ndarray, margin_m: float = 0.0
) -> tuple[list[np.ndarray], np.ndarray]:
    """Indices `(m_i,)` int64 of each box's points above its ground height (first box wins),
    and the number of the box's points below it `(k,)` int32. `margin_m`: the box grown by this
    on every side (a LiDAR point lies on the car's surface, i.e. on its true box's boundary: an
    imprecise pseudo box leaves part of the car outside it, as raw points beside the model)."""
    members = points_per_box(points, boxes, margin_m)
    height = points[:, 2]  # a strided view: gathering from it beats points[idx, 2]
    cars = [idx[height[idx] >= z] for idx, z in zip(members, ground_z, strict=True)]
    ground = np.array([len(m) - len(c) for m, c in zip(members, cars, strict=True)], np.int32)
    return cars, ground


@dataclass
class BoxRecords:
    """Per-box outcome of one frame, all `(k,)`: ppcg (rc|cf|raw), reason (REASONS),
    points_before / points_after (car points in the box before/after), ground_points (points
    in the box below its ground height, kept), model_id ("" if none), flipped (the model was
    fitted turned round: the box's heading was turned by pi, dali_cli.ppcg.orient)."""

    ppcg: np.ndarray
    reason: np.ndarray
    points_before: np.ndarray
    points_after: np.ndarray
    ground_points: np.ndarray
    model_id: np.ndarray
    flipped: np.ndarray

    @classmethod
    def raw(cls, points_before: np.ndarray, ground_points: np.ndarray | None = None) -> BoxRecords:
        count = len(points_before)
        before = np.asarray(points_before, dtype=np.int32)
        ground = np.zeros(count, np.int32) if ground_points is None else ground_points
        return cls(
            ppcg=np.full(count, RAW, dtype=object),
            reason=np.full(count, "ok", dtype=object),
            points_before=before,
            points_after=before.copy(),
            ground_points=np.asarray(ground, dtype=np.int32),
            model_id=np.full(count, "", dtype=object),
            flipped=np.zeros(count, dtype=bool),
        )


def assemble(
    points: np.ndarray,
    removed: list[np.ndarray],
    replaced: list[tuple[np.ndarray, np.ndarray]],
    added: list[np.ndarray],
) -> np.ndarray:
    """The new frame `(n', 4)` float32: rows `replaced` (index, xyz) get new coordinates, rows
    `removed` go, `added` `(a, 4)` rows are appended. Untouched points keep their order."""
    out = np.array(points, dtype=np.float32, order="C", copy=True)
    for index, xyz in replaced:
        out[index, :3] = xyz
    if removed:
        gone = np.concatenate(removed)
        if len(gone):
            keep = np.ones(len(out), dtype=bool)
            keep[gone] = False
            # one 16-byte item per row: boolean selection is ~15x faster than on (n, 4) rows
            out = out.view(np.complex128).reshape(-1)[keep].view(np.float32).reshape(-1, 4)
    if added:
        out = np.concatenate([out, *[np.asarray(a, dtype=np.float32) for a in added]])
    return out
