"""Which points of a frame lie in which box, fast enough for a 120k-point frame with ~15 boxes.

A coarse BEV grid over the boxes' bounding squares picks the few candidate points near any box in
one pass over the frame; the exact rotated-box test then runs on those candidates only.
"""

from __future__ import annotations

import numpy as np

_CELL_M = 1.0


def points_per_box(
    points: np.ndarray, boxes: np.ndarray, margin_m: float = 0.0
) -> list[np.ndarray]:
    """Indices of the points inside each box, `k` arrays of int64, ascending and disjoint.

    points `(n, >=3)` sensor frame; boxes `(k, 7)`; margin_m enlarges every box on all sides.
    A point inside several boxes belongs to the first (as geometry.point_box_indices).
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    if len(boxes) == 0:
        return []
    half_diagonal = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4]) + margin_m  # (k,)
    # grid over the boxes' bounding squares plus one border cell on each side (index 0 and last)
    lower = (boxes[:, :2] - half_diagonal[:, None]).min(axis=0) - _CELL_M  # (2,)
    upper = (boxes[:, :2] + half_diagonal[:, None]).max(axis=0) + _CELL_M
    shape = np.ceil((upper - lower) / _CELL_M).astype(np.int64) + 1  # (2,) cells
    marked = np.zeros((int(shape[0]), int(shape[1])), dtype=bool)
    first_cell = np.floor((boxes[:, :2] - half_diagonal[:, None] - lower) / _CELL_M).astype(
        np.int64
    )
    last_cell = np.floor((boxes[:, :2] + half_diagonal[:, None] - lower) / _CELL_M).astype(np.int64)
    for first, last in zip(first_cell, last_cell, strict=True):  # loop over boxes
        marked[first[0] : last[0] + 1, first[1] : last[1] + 1] = True
    # one pass per axis on float32 columns; clipping sends every outside point to a border cell
    flat = None
    for axis in (0, 1):
        scaled = points[:, axis] - np.float32(lower[axis])  # (n,) float32
        scaled *= np.float32(1.0 / _CELL_M)
        np.clip(scaled, 0.0, float(shape[axis] - 1), out=scaled)
        index = scaled.astype(np.intp)
        if flat is None:
            flat = index
        else:
            flat *= int(shape[1])
            flat += index
    candidates = np.flatnonzero(marked.reshape(-1)[flat])  # (c,) ascending
    candidate_cells = flat[candidates]
    order = np.argsort(candidate_cells, kind="stable")  # candidates grouped by cell
    sorted_cells = candidate_cells[order]
    # each box covers one contiguous run of flat cell indices per grid row: all runs at once
    row_counts = last_cell[:, 0] - first_cell[:, 0] + 1  # (k,)
    run_box = np.repeat(np.arange(len(boxes)), row_counts)  # (r,)
    run_row = (
        first_cell[run_box, 0]
        + np.arange(len(run_box))
        - np.repeat(np.cumsum(row_counts) - row_counts, row_counts)
    )
    starts = np.searchsorted(sorted_cells, run_row * shape[1] + first_cell[run_box, 1], side="left")
    stops = np.searchsorted(sorted_cells, run_row * shape[1] + last_cell[run_box, 1], side="right")
    lengths = stops - starts  # (r,)
    pair_box = np.repeat(run_box, lengths)  # (p,) candidate-box pairs
    pair_slot = np.arange(int(lengths.sum())) - np.repeat(
        np.cumsum(lengths) - lengths - starts, lengths
    )
    pair_candidate = order[pair_slot]  # (p,) position in `candidates`
    near = np.take(points, candidates[pair_candidate], axis=0)  # (p, >=3) float32
    cos, sin = np.cos(boxes[pair_box, 6]), np.sin(boxes[pair_box, 6])
    dx = near[:, 0] - boxes[pair_box, 0]
    dy = near[:, 1] - boxes[pair_box, 1]
    local_x = cos * dx + sin * dy
    local_y = cos * dy - sin * dx
    hit = (
        (np.abs(local_x) <= 0.5 * boxes[pair_box, 3] + margin_m)
        & (np.abs(local_y) <= 0.5 * boxes[pair_box, 4] + margin_m)
        & (np.abs(near[:, 2] - boxes[pair_box, 2]) <= 0.5 * boxes[pair_box, 5] + margin_m)
    )
    pair_box, pair_point = pair_box[hit], candidates[pair_candidate[hit]]
    # first box wins: sort by (point, box) and keep each point's first pair
    by_point = np.lexsort((pair_box, pair_point))
    pair_box, pair_point = pair_box[by_point], pair_point[by_point]
    first = np.r_[True, pair_point[1:] != pair_point[:-1]]
    pair_box, pair_point = pair_box[first], pair_point[first]
    by_box = np.argsort(pair_box, kind="stable")  # points stay ascending within each box
    bounds = np.searchsorted(pair_box[by_box], np.arange(len(boxes) + 1))
    pair_point = pair_point[by_box]
    return [pair_point[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
