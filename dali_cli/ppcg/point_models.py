"""Ray casting against point models: for each ray, the model point nearest the sensor within an angle.

A point model has no surface, so a ray "hits" the model points whose direction from the ray origin
is within theta_th of the ray (METHOD: theta_th = 2 x 360 deg / points per beam); the hit is the one
nearest the origin. dali puts the returned point on the ray at that model point's range, so the
output keeps the sensor's ray pattern exactly.

The search uses an angular index instead of an n x m angle matrix: unit directions are bucketed in
a 3-D grid whose cell is the chord 2 sin(theta/2), so every neighbour within theta lies in the 27
cells around a ray's cell; candidate pairs come from sorted keys and searchsorted ranges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_OFFSETS = np.stack(
    np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), axis=-1
).reshape(27, 3)


def angular_threshold_rad(points_per_beam: int) -> float:
    """theta_th = 2 x (360 deg / points per beam), in radians (METHOD, PPCG RC)."""
    return 2.0 * (2.0 * np.pi / points_per_beam)


@dataclass(frozen=True)
class PointHits:
    """Result per ray `(N,)`: hit bool, model_index int64 (-1 on miss), distance float64 (inf on
    miss, along the unit ray) and points `(N, 3)` float64 (origin + distance * direction, NaN on miss)."""

    hit: np.ndarray
    model_index: np.ndarray
    distance: np.ndarray
    points: np.ndarray


def _unit(vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    norm = np.linalg.norm(vectors, axis=1)
    return vectors / np.maximum(norm, 1e-12)[:, None], norm


def _grid_keys(cells: np.ndarray, size: int) -> np.ndarray:
    """Integer cells `(..., 3)` in [0, size) -> one int64 key each."""
    return (cells[..., 0] * size + cells[..., 1]) * size + cells[..., 2]


def cast_point_model(
    origin: np.ndarray,
    directions: np.ndarray,
    model_points: np.ndarray,
    theta_rad: float,
) -> PointHits:
    """First hits of rays on a point cloud, by angular proximity (see module docstring).

    origin `(3,)` sensor position; directions `(N, 3)` (normalized here); model_points `(M, 3)`
    in the same frame (a point model already placed in its box). Ties in range go to the lower
    model index. Memory is proportional to the candidate pairs, never N x M.
    """
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    rays, _ = _unit(np.asarray(directions, dtype=np.float64).reshape(-1, 3))
    relative = np.asarray(model_points, dtype=np.float64).reshape(-1, 3) - origin
    units, ranges = _unit(relative)
    count = len(rays)
    model_index = np.full(count, -1, dtype=np.int64)
    distance = np.full(count, np.inf)
    if count and len(units):
        cell = 2.0 * np.sin(0.5 * theta_rad)  # chord of theta: |u - v| <= cell  <=>  angle <= theta
        size = int(np.ceil(2.0 / cell)) + 4
        model_cells = np.floor(units / cell).astype(np.int64) + size // 2
        ray_cells = np.floor(rays / cell).astype(np.int64) + size // 2
        model_keys = _grid_keys(model_cells, size)  # (M,)
        order = np.argsort(model_keys, kind="stable")  # model points grouped by cell
        sorted_keys = model_keys[order]
        by_range = np.argsort(ranges, kind="stable")  # ties: the lower model index first
        rank = np.empty(len(ranges), dtype=np.int64)
        rank[by_range] = np.arange(len(ranges))
        sorted_units, sorted_rank = units[order], rank[order]
        query = _grid_keys(ray_cells[:, None, :] + _OFFSETS[None, :, :], size).reshape(-1)
        lo = np.searchsorted(sorted_keys, query, side="left")  # (N*27,) candidate runs
        counts = np.searchsorted(sorted_keys, query, side="right") - lo
        total = int(counts.sum())
        if total:
            # candidate pairs come ray by ray: ray i owns per_ray[i] consecutive pairs
            per_ray = counts.reshape(count, 27).sum(axis=1)  # (N,)
            first_of_run = np.cumsum(counts) - counts  # exclusive prefix sum, (N*27,)
            position = np.arange(total) - np.repeat(first_of_run - lo, counts)  # (P,)
            cosine = np.einsum(
                "ij,ij->i", np.repeat(rays, per_ray, axis=0), sorted_units[position]
            )  # (P,)
            miss = len(ranges)
            key = np.where(cosine >= np.cos(theta_rad), sorted_rank[position], miss)  # (P,)
            has = per_ray > 0
            best = np.full(count, miss, dtype=np.int64)
            best[has] = np.minimum.reduceat(key, (np.cumsum(per_ray) - per_ray)[has])
            found = best < miss
            model_index[found] = by_range[best[found]]
            distance[found] = ranges[model_index[found]]
    hit = model_index >= 0
    points = np.full((count, 3), np.nan)
    points[hit] = origin + distance[hit, None] * rays[hit]
    return PointHits(hit, model_index, distance, points)


def cast_point_model_bruteforce(
    origin: np.ndarray, directions: np.ndarray, model_points: np.ndarray, theta_rad: float
) -> PointHits:
    """Reference for tests: the same result from the full N x M angle matrix (small inputs only)."""
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    rays, _ = _unit(np.asarray(directions, dtype=np.float64).reshape(-1, 3))
    units, ranges = _unit(np.asarray(model_points, dtype=np.float64).reshape(-1, 3) - origin)
    within = rays @ units.T >= np.cos(theta_rad)  # (N, M)
    masked = np.where(within, ranges[None, :], np.inf)
    model_index = np.where(within.any(axis=1), np.argmin(masked, axis=1), -1).astype(np.int64)
    hit = model_index >= 0
    distance = np.where(hit, masked.min(axis=1) if len(units) else np.inf, np.inf)
    points = np.full((len(rays), 3), np.nan)
    points[hit] = origin + distance[hit, None] * rays[hit]
    return PointHits(hit, model_index, distance, points)
