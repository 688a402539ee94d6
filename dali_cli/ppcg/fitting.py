"""Model selection and placement: which library model fits a pseudo box, and the box <-> model maps.

Library models live in a unit box centred at the origin (l along +x, w along +y, h along +z).
Fitting scales a model anisotropically to the box's (l, w, h) and places it at the box's pose, so
a model point p maps to the sensor frame as `A @ p + t` with `A = R(yaw) @ diag(l, w, h)` and `t`
the box centre. Rays are moved into the model frame instead (`A^-1 (o - t)`, `A^-1 d`): the ray
parameter is unchanged by an affine map, so a hit at parameter s is `o + s d` in the sensor frame.

Randomness (top-k picks, CF ranges) comes from `box_rng(seed, frame_id, box_index)`, so results
do not depend on worker count or processing order.
"""

from __future__ import annotations

import hashlib

import numpy as np

from dali_cli.geometry import wrap_angle


def box_rng(seed: int, frame_id: str, box_index: int) -> np.random.Generator:
    """A generator seeded by (run seed, frame id, index of the box within its frame)."""
    digest = hashlib.blake2b(str(frame_id).encode(), digest_size=8).digest()
    words = np.frombuffer(digest, dtype=np.uint32).tolist()
    return np.random.default_rng(
        np.random.SeedSequence([int(seed) & 0xFFFFFFFF, *words, int(box_index)])
    )


def box_uniform(seed: int, frame_id: str, box_index: int, stream: str) -> float:
    """One uniform draw in [0, 1) keyed by (run seed, frame id, box index, stream name).

    A hash instead of a generator: ~50x cheaper than building a Generator per box, and a new
    stream name never shifts the draws of another.
    """
    key = f"{int(seed)}\0{frame_id}\0{int(box_index)}\0{stream}".encode()
    value = int.from_bytes(hashlib.blake2b(key, digest_size=8).digest(), "little")
    return (value >> 11) * 2.0**-53


# ---------------------------------------------------------------------------------------------
# Placement


def box_affine(box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit-box model frame -> sensor frame for one box `(7,)`: `(A (3, 3), t (3,))` float64."""
    x, y, z, length, width, height, yaw = (float(v) for v in box)
    cos, sin = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]])
    return rotation * np.array([length, width, height]), np.array([x, y, z])


def box_affine_inverse(box: np.ndarray) -> np.ndarray:
    """`A^-1` `(3, 3)` of `box_affine` in closed form: diag(1/l, 1/w, 1/h) R(yaw)^T."""
    length, width, height, yaw = (float(v) for v in box[3:7])
    cos, sin = np.cos(yaw), np.sin(yaw)
    rotation_t = np.array([[cos, sin, 0.0], [-sin, cos, 0.0], [0.0, 0.0, 1.0]])
    return rotation_t / np.array([[length], [width], [height]])


def model_to_sensor(points_unit: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Model-frame points `(M, 3)` placed in `box` `(7,)` -> sensor-frame points `(M, 3)` float64."""
    matrix, translation = box_affine(box)
    return np.asarray(points_unit, dtype=np.float64) @ matrix.T + translation


def sensor_to_model(points: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Sensor-frame points `(M, 3)` -> unit-box model frame of `box` `(7,)`, `(M, 3)` float64."""
    translation = np.asarray(box[:3], dtype=np.float64)
    return (np.asarray(points, dtype=np.float64) - translation) @ box_affine_inverse(box).T


def rays_to_model(
    origins: np.ndarray, directions: np.ndarray, box: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rays `(N, 3)`, `(N, 3)` in the sensor frame -> the same rays in the model frame of `box`.

    Directions are not renormalized: a hit at parameter s in the model frame is at `o + s d` in
    the sensor frame. `origins` may be `(3,)` (one origin shared by all rays).
    """
    translation = np.asarray(box[:3], dtype=np.float64)
    inverse = box_affine_inverse(box)
    origins = np.asarray(origins, dtype=np.float64)
    return (origins - translation) @ inverse.T, np.asarray(directions, np.float64) @ inverse.T


# ---------------------------------------------------------------------------------------------
# Selection


def size_cost(box_lwh: np.ndarray, model_lwh: np.ndarray) -> np.ndarray:
    """sum over l, w, h of |model / box - 1|: boxes `(N, 3)`, models `(M, 3)` -> `(N, M)`."""
    box_lwh = np.asarray(box_lwh, dtype=np.float64).reshape(-1, 1, 3)
    model_lwh = np.asarray(model_lwh, dtype=np.float64).reshape(1, -1, 3)
    return np.abs(model_lwh / box_lwh - 1.0).sum(axis=2)


def pick_ranked(order: np.ndarray, top_k: int, rng: np.random.Generator | None) -> int:
    """The first of `order` (best first) when top_k <= 1, else a uniform pick among its first k."""
    if top_k <= 1 or rng is None or len(order) == 1:
        return int(order[0])
    return int(order[rng.integers(min(top_k, len(order)))])


def select_cad_models(
    box_lwh: np.ndarray,
    model_lwh: np.ndarray,
    top_k: int = 1,
    rngs: list[np.random.Generator] | None = None,
) -> np.ndarray:
    """Index of the fitted mesh for each box: smallest size cost, or random among the k best.

    box_lwh `(N, 3)`, model_lwh `(M, 3)` native model sizes (m); rngs one per box (top_k > 1).
    Returns `(N,)` int64. Ties go to the lower model index (stable sort).
    """
    cost = size_cost(box_lwh, model_lwh)  # (N, M)
    if top_k <= 1:
        return np.argmin(cost, axis=1).astype(np.int64)
    k = min(top_k, cost.shape[1])
    best = np.argpartition(cost, k - 1, axis=1)[:, :k] if k < cost.shape[1] else None
    picks = np.empty(len(cost), dtype=np.int64)
    for row in range(len(cost)):  # loop over boxes (~15 per frame), not points
        candidates = np.arange(cost.shape[1]) if best is None else np.sort(best[row])
        order = candidates[np.argsort(cost[row, candidates], kind="stable")]
        picks[row] = pick_ranked(order, top_k, None if rngs is None else rngs[row])
    return picks


def circular_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Absolute angular difference in [0, pi] of broadcastable angle arrays (rad)."""
    difference = np.mod(np.asarray(a, np.float64) - np.asarray(b, np.float64), 2.0 * np.pi)
    return np.minimum(difference, 2.0 * np.pi - difference)


def viewing_angle(boxes: np.ndarray) -> np.ndarray:
    """Azimuth of the sensor seen from each box, in the box frame: `(N,)` rad in [-pi, pi).

    boxes `(N, 7)`. As library.PointModels.view_angle_rad: atan2 of the box-frame sensor position,
    so 0 means the sensor is ahead of the car (it sees the front), pi behind it (it sees the back).
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    return wrap_angle(np.arctan2(-boxes[:, 1], -boxes[:, 0]) - boxes[:, 6])


def select_point_models(
    box_angle: np.ndarray,
    box_lwh: np.ndarray,
    model_angle: np.ndarray,
    model_lwh: np.ndarray,
    angle_tolerance_rad: float = np.radians(5.0),
    top_k: int = 1,
    rngs: list[np.random.Generator] | None = None,
) -> np.ndarray:
    """Index of the point model for each box: nearest viewing angle, then best size fit.

    box_angle `(N,)`, model_angle `(M,)` viewing angles (rad, see `viewing_angle`); box_lwh
    `(N, 3)`, model_lwh `(M, 3)` sizes (m). Candidates are the models whose circular angle
    distance is within `angle_tolerance_rad` of the nearest model's; among them the smallest
    size cost wins (or a random one of the k smallest). Uses a sorted angle index: no N x M work.
    Returns `(N,)` int64.
    """
    model_angle = np.mod(np.asarray(model_angle, dtype=np.float64), 2.0 * np.pi)
    box_angle = np.mod(np.asarray(box_angle, dtype=np.float64).reshape(-1), 2.0 * np.pi)
    model_lwh = np.asarray(model_lwh, dtype=np.float64).reshape(-1, 3)
    box_lwh = np.asarray(box_lwh, dtype=np.float64).reshape(-1, 3)
    count = len(model_angle)
    if count == 0:
        raise ValueError("no point models to select from")
    order = np.argsort(model_angle, kind="stable")
    sorted_angle = model_angle[order]
    # nearest model angle: the neighbours of the insertion point, with wrap-around
    position = np.searchsorted(sorted_angle, box_angle)  # (N,)
    neighbours = np.stack([(position - 1) % count, position % count], axis=1)  # (N, 2)
    nearest = circular_distance(sorted_angle[neighbours], box_angle[:, None]).min(axis=1)  # (N,)
    reach = nearest + angle_tolerance_rad + 1e-9  # the epsilon keeps the nearest model itself
    picks = np.empty(len(box_angle), dtype=np.int64)
    for row in range(len(box_angle)):  # loop over boxes, each a few searchsorted calls
        lo, hi = box_angle[row] - reach[row], box_angle[row] + reach[row]
        candidates = _angle_interval(sorted_angle, lo, hi)
        if reach[row] >= np.pi:
            candidates = np.arange(count)
        candidates = order[candidates]
        cost = size_cost(box_lwh[row], model_lwh[candidates])[0]
        ranked = candidates[np.lexsort((candidates, cost))]
        picks[row] = pick_ranked(ranked, top_k, None if rngs is None else rngs[row])
    return picks


def _angle_interval(sorted_angle: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Positions in `sorted_angle` (ascending, in [0, 2 pi)) of angles within [lo, hi] mod 2 pi."""
    two_pi = 2.0 * np.pi
    parts = []
    for shift in (-two_pi, 0.0, two_pi):  # the interval may wrap past 0 or 2 pi
        a = np.searchsorted(sorted_angle, lo + shift, side="left")
        b = np.searchsorted(sorted_angle, hi + shift, side="right")
        if b > a:
            parts.append(np.arange(a, b))
    return np.unique(np.concatenate(parts)) if parts else np.zeros(0, dtype=np.int64)
