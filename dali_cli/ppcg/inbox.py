"""Which points of a frame lie in which box, fast enough for a 120k-point frame with ~15 boxes.

A coarse BEV grid over the boxes' bounding squares picks the few candidate points near any box in
one pass over the frame; the exact rotated-box test then runs on those candidates only.
"""

from __future__ import annotations

import numpy as np

from dali_cli.geometry import box_frames, inside_box_frames

_CELL_M = 1.0  # grid cell (m) unless the boxes spread over more than _MAX_CELLS cells
_MAX_CELLS = 2**20
_NONE, _SHARED = -1, -2  # cell owners that are not a box index


def points_per_box(
    points: np.ndarray, boxes: np.ndarray, margin_m: float = 0.0
) -> list[np.ndarray]:
    """Indices of the points inside each box, `k` arrays of int64, disjoint, each ascending.

    points `(n, >=3)` sensor frame; boxes `(k, 7)`; margin_m enlarges every box on all sides.
    A point inside several boxes belongs to the first (as geometry.point_box_indices).
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    if len(boxes) == 0:
        return []
    half_diagonal = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4]) + margin_m  # (k,)
    # grid over the boxes' bounding squares plus one border cell on each side (index 0 and last);
    # cells grow when boxes are spread very far apart, so the grid stays small
    span = (boxes[:, :2] + half_diagonal[:, None]).max(axis=0) - (
        boxes[:, :2] - half_diagonal[:, None]
    ).min(axis=0)
    cell_m = max(_CELL_M, float(np.sqrt(np.prod(span + 2 * _CELL_M) / _MAX_CELLS)))
    lower = (boxes[:, :2] - half_diagonal[:, None]).min(axis=0) - cell_m  # (2,)
    upper = (boxes[:, :2] + half_diagonal[:, None]).max(axis=0) + cell_m
    shape = np.ceil((upper - lower) / cell_m).astype(np.int64) + 1  # (2,) cells
    # cell -> the one box whose bounding square covers it, SHARED if several, NONE if none
    owner_of_cell = np.full((int(shape[0]), int(shape[1])), _NONE, dtype=np.int64)
    first_cell = np.floor((boxes[:, :2] - half_diagonal[:, None] - lower) / cell_m).astype(np.int64)
    last_cell = np.floor((boxes[:, :2] + half_diagonal[:, None] - lower) / cell_m).astype(np.int64)
    for box_index, (first, last) in enumerate(zip(first_cell, last_cell, strict=True)):
        block = owner_of_cell[first[0] : last[0] + 1, first[1] : last[1] + 1]  # a view
        block[block != _NONE] = _SHARED
        block[block == _NONE] = box_index
    # one pass per axis on float32 columns; clipping sends every outside point to a border cell
    flat = None
    for axis in (0, 1):
        scaled = points[:, axis] - np.float32(lower[axis])  # (n,) float32
        scaled *= np.float32(1.0 / cell_m)
        np.clip(scaled, 0.0, float(shape[axis] - 1), out=scaled)
        index = scaled.astype(np.intp)
        if flat is None:
            flat = index
        else:
            flat *= int(shape[1])
            flat += index
    cell_owner = owner_of_cell.reshape(-1)[flat]  # (n,)
    candidates = np.flatnonzero(cell_owner != _NONE)  # (c,) ascending
    # group candidates by cell owner (a stable radix sort on int16 keeps them ascending per group)
    key_type = np.int16 if len(boxes) < 2**15 else np.int32
    order = np.argsort(cell_owner[candidates].astype(key_type), kind="stable")
    candidates = candidates[order]
    bounds = np.searchsorted(cell_owner[candidates], np.arange(_SHARED, len(boxes) + 1))
    near = np.take(points, candidates, axis=0)  # (c, >=3) float32, grouped by owner
    frames = box_frames(boxes, margin_m, near.dtype)  # per box, once
    # bounds: [shared start, shared end (no NONE owner is left), box 0 start, ..., box k-1 end]
    start = bounds[2]  # cells of one box: test against that box only
    counts = np.diff(bounds[2:])  # (k,) candidates per box, in box order
    inside = inside_box_frames(
        near[start:, :3], *(np.repeat(p, counts, axis=0) for p in frames)
    )  # (c - s,)
    members = [
        candidates[a:b][inside[a - start : b - start]]
        for a, b in zip(bounds[2:-1], bounds[3:], strict=True)
    ]
    shared = candidates[bounds[0] : bounds[1]]  # cells several boxes cover: first box wins
    if len(shared):
        hits = inside_box_frames(near[bounds[0] : bounds[1], None, :3], *frames)  # (s, k)
        first = np.where(hits.any(axis=1), hits.argmax(axis=1), -1)
        for box_index in np.unique(first[first >= 0]):
            members[box_index] = np.sort(
                np.concatenate([members[box_index], shared[first == box_index]])
            )
    return members
