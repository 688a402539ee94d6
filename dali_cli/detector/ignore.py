"""Ignore regions of training: boxes over which the detector is taught neither "car" nor
"background".

A pseudo-labelled frame holds cars the labeller scored just under its cut (`dali pseudo-label
--ignore-min` writes them with the label IGNORE_LABEL). Left as they are they are background
to every loss, so retraining learns to miss the very cars the labeller was unsure of; made
cars (score >= the cut) they would add false boxes. As ignore regions they supervise nothing:
the heatmap's negative term is off in the head cells they cover, and the IoU head and the
refiner are not trained on peaks / proposals centred in them. Positives are never ignored.

Measured (docs/RESULTS.md, session 30, seed 0): with the 0.3-0.6 band as regions and the cars
cut at 0.6 the 1:7 retraining gains +0.39 +- 0.29 AP_3D over the 0.3 boxes, but the 0.6 cut alone
as much (the regions +0.03 +- 0.28); level at 1:1. Off by default.

Boxes: (k, 7) float64 x, y, z, l, w, h, yaw in the ground frame (detector/config.py); BEV tests
only (an ignore region is a column over its footprint).
"""

from __future__ import annotations

import numpy as np

from dali_cli.detector.config import DetectorConfig

IGNORE_LABEL = "DontCare"  # pseudo-label --ignore-min's label; KITTI's name for the same idea
MARGIN_M = 0.5  # footprints grow by this on each side: the heat around a car spreads past it


def inside_footprints(xy: np.ndarray, boxes: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
    """(N,) bool: which points xy (N, 2) (m) lie inside the BEV footprint of any box (k, 7),
    each side grown by `margin_m`."""
    from dali_cli.geometry import box_frames, inside_box_frames

    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    if len(boxes) == 0 or len(xy) == 0:
        return np.zeros(len(xy), bool)
    cos, sin, centre, half = box_frames(boxes, margin_m, np.float64)  # (k,), (k, 3)
    shape = (len(xy), len(boxes))
    xyz = np.concatenate(  # (N, k, 3): each point at each box's own height (a BEV test)
        [
            np.broadcast_to(xy[:, None, :], (*shape, 2)),
            np.broadcast_to(centre[:, 2:3], (*shape, 1)),
        ],
        axis=-1,
    )
    return inside_box_frames(xyz, cos, sin, centre, half).any(axis=1)


def ignored_cells(boxes: np.ndarray, config: DetectorConfig) -> np.ndarray:
    """(h, w) bool over the head grid: cells whose centre lies in an ignore box's footprint
    (grown by MARGIN_M)."""
    h, w = config.head_size
    mask = np.zeros((h, w), bool)
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    if len(boxes) == 0:
        return mask
    reach = np.hypot(boxes[:, 3], boxes[:, 4]) / 2 + MARGIN_M  # (k,) a circle around each box
    col0 = np.floor((boxes[:, 0] - reach - config.x_range_m[0]) / config.cell_m).astype(int)
    col1 = np.ceil((boxes[:, 0] + reach - config.x_range_m[0]) / config.cell_m).astype(int)
    row0 = np.floor((boxes[:, 1] - reach - config.y_range_m[0]) / config.cell_m).astype(int)
    row1 = np.ceil((boxes[:, 1] + reach - config.y_range_m[0]) / config.cell_m).astype(int)
    for j in range(len(boxes)):  # a few boxes per frame, each a small window of cells
        c0, c1 = max(col0[j], 0), min(col1[j] + 1, w)
        r0, r1 = max(row0[j], 0), min(row1[j] + 1, h)
        if c0 >= c1 or r0 >= r1:
            continue
        rows, cols = np.mgrid[r0:r1, c0:c1]
        xy = np.stack(
            [
                config.x_range_m[0] + (cols.ravel() + 0.5) * config.cell_m,
                config.y_range_m[0] + (rows.ravel() + 0.5) * config.cell_m,
            ],
            axis=1,
        )
        mask[r0:r1, c0:c1] |= inside_footprints(xy, boxes[j : j + 1], MARGIN_M).reshape(rows.shape)
    return mask


def ignored_centres(boxes: np.ndarray, ignore: np.ndarray | None) -> np.ndarray:
    """(K,) bool: which boxes (K, 7) (peaks' decoded boxes, refiner proposals) have their centre
    in an ignore region (k, 7) (footprint grown by MARGIN_M); all False without one."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    if ignore is None or len(ignore) == 0:
        return np.zeros(len(boxes), bool)
    return inside_footprints(boxes[:, :2], ignore, MARGIN_M)
