"""LiDAR poses by scan registration: each scan aligned to a local map of the scans before it
(point-to-plane ICP in the spirit of KISS-ICP, Vizzo et al., RA-L 2023), for sequences recorded
without GPS/IMU poses. Why not through the `kiss-icp` package: docs/tracks.md.

Plain numpy. Points are `(n, >= 3)` float in a scan's LiDAR frame (metres); a pose is `(4, 4)`
float64, the scan's LiDAR frame in the first scan's (x_first = pose @ [x_scan, 1]).

Per scan: points nearer than `min_range_m` (the ego car) or beyond `max_range_m` are dropped; the
rest are thinned to one point per `voxel_m / 2` voxel (what enters the map) and again per
`1.5 voxel_m` voxel (what is registered). The scan's pose is predicted by constant velocity (the
last step repeated) and refined by Gauss-Newton on point-to-plane residuals to the nearest map
point (point-to-point where the map around that point is no surface; none where it is a line or
too sparse to tell), each weighted by a Geman-McClure kernel that narrows from
`max_correspondence_m` to `kernel_m`; it stops when an update moves less than `tolerance`
(metres + radians) at the final kernel, or after `max_iterations`. The map is a voxel hash
(`voxel_m`, at most `max_points_per_voxel` points each, the oldest kept) of the registered
scans, cut to `max_range_m` around the latest pose; its nearest-neighbour search looks in the 27
voxels around a point (sorted keys + searchsorted).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

_BITS = 21  # per axis in a packed voxel key: +-2^20 voxels (+-1000 km at 1 m)
_BIAS = 1 << (_BITS - 1)
_NEIGHBOURS = np.array(
    [(dx << (2 * _BITS)) + (dy << _BITS) + dz
     for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)],
    np.int64,
)  # (27,) key offsets of a voxel's neighbours  # fmt: skip
_QUERY_BLOCK = 2048  # queries searched at once: bounds the candidate pairs held in memory
MIN_SCAN_POINTS = 100  # registered points (after cropping and thinning) a scan needs
_SHAPE_MIN_POINTS = 5  # points a map voxel's neighbourhood needs for a shape
_FLAT_RATIO = 0.1  # eigenvalue ratio under which a covariance is flat along an axis
# a map voxel's shape: a surface (point-to-plane residuals); a line (a scan ring on the ground or
# a pole) or too few points to tell (far ground): no residual, since a scan's rings match the
# map's rings best where the sensor has not moved; anything else (point-to-point)
SCATTERED, PLANAR, LINEAR, SPARSE = 0, 1, 2, 3


class RegistrationError(ValueError):
    """A sequence that cannot be registered; `scan` is the position of the offending scan."""

    def __init__(self, scan: int, message: str):
        self.scan = scan
        super().__init__(message)


@dataclass(frozen=True)
class RegistrationParams:
    """voxel_m: map voxel edge (m); the scan is kept at half of it and registered at 1.5 times
    it. min_range_m / max_range_m: points nearer / farther from the sensor are dropped.
    max_correspondence_m: a point farther than this from its nearest map point has no
    residual, and the first kernel scale. kernel_m: the final Geman-McClure scale (m) of the
    residuals. max_iterations / tolerance: ICP stops after this many updates, or at an update
    smaller than tolerance (translation m + rotation rad). max_points_per_voxel: map points a voxel keeps.
    motion_prior: start each scan at the constant-velocity prediction (else at the last pose)."""

    voxel_m: float = 1.0
    min_range_m: float = 3.0
    max_range_m: float = 80.0
    max_correspondence_m: float = 1.5
    kernel_m: float = 0.3
    max_iterations: int = 50
    tolerance: float = 1e-4
    max_points_per_voxel: int = 20
    motion_prior: bool = True


@dataclass
class Registration:
    """poses: `(n, 4, 4)` float64 scan poses in the first scan's frame; iterations: `(n,)` int
    ICP updates per scan (0 for the first); converged: `(n,)` bool (False: the cap was hit);
    points: `(n,)` int points registered per scan."""

    poses: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    points: np.ndarray


# ---------------------------------------------------------------------------------------------
# Voxels


def voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """`(n,)` int64 packed integer voxel coordinates of `(n, >= 3)` points (m)."""
    cells = np.floor(np.asarray(points, np.float64)[:, :3] / voxel_m).astype(np.int64) + _BIAS
    if len(cells) and (cells.min() < 1 or cells.max() >= (1 << _BITS) - 1):
        raise ValueError(f"points beyond +-{_BIAS - 1} voxels of {voxel_m} m from the origin")
    return (cells[:, 0] << (2 * _BITS)) | (cells[:, 1] << _BITS) | cells[:, 2]


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """The first of `(n, d)` points in each `voxel_m` voxel, in their input order."""
    _, first = np.unique(voxel_keys(points, voxel_m), return_index=True)
    return points[np.sort(first)]


def crop_range(points: np.ndarray, min_range_m: float, max_range_m: float) -> np.ndarray:
    """`(m, 3)` float64 of `(n, >= 3)` points whose distance from the sensor is in
    [min_range_m, max_range_m]."""
    xyz = np.asarray(points, np.float64)[:, :3]
    distance = np.linalg.norm(xyz, axis=1)
    return xyz[(distance >= min_range_m) & (distance <= max_range_m)]


def add_to_map(
    map_points: np.ndarray, points: np.ndarray, voxel_m: float, max_per_voxel: int
) -> np.ndarray:
    """`(m', 3)` the map `(m, 3)` with `(k, 3)` new points, each voxel holding at most
    `max_per_voxel` points (the map's own first, then the new ones in order)."""
    merged = np.concatenate([map_points, points])
    keys = voxel_keys(merged, voxel_m)
    order = np.argsort(keys, kind="stable")  # (m + k,) voxel by voxel, old points first
    sorted_keys = keys[order]
    start = np.r_[0, np.flatnonzero(np.diff(sorted_keys)) + 1]  # (V,) first row of each voxel
    counts = np.diff(np.r_[start, len(sorted_keys)])
    rank = np.arange(len(sorted_keys)) - np.repeat(start, counts)  # position within the voxel
    return merged[np.sort(order[rank < max_per_voxel])]


@dataclass
class VoxelIndex:
    """A map indexed for nearest-neighbour search: points sorted by voxel; per voxel its key,
    first row, count, unit normal and shape (SCATTERED, PLANAR, LINEAR)."""

    voxel_m: float
    points: np.ndarray  # (m, 3) float64, sorted by voxel key
    voxel_of: np.ndarray  # (m,) int64 voxel of each point
    keys: np.ndarray  # (V,) int64 ascending
    start: np.ndarray  # (V,) int64
    count: np.ndarray  # (V,) int64
    normals: np.ndarray  # (V, 3) float64
    shape: np.ndarray  # (V,) int64


def index_map(map_points: np.ndarray, voxel_m: float) -> VoxelIndex:
    """The VoxelIndex of `(m, 3)` map points. A voxel's shape and normal come from the
    covariance of the points in it and its 26 neighbours (at least 5, else it is SPARSE):
    LINEAR when the two largest eigenvalues differ by 10x or more, else PLANAR when the two
    least do (its normal: the least eigenvector), else SCATTERED."""
    keys = voxel_keys(map_points, voxel_m)
    order = np.argsort(keys, kind="stable")
    points, keys = map_points[order], keys[order]
    start = np.r_[0, np.flatnonzero(np.diff(keys)) + 1]
    count = np.diff(np.r_[start, len(keys)])
    voxel_of = np.repeat(np.arange(len(start)), count)
    unique = keys[start]
    local = points - points[0]  # moments about one map point: no cancellation far away
    first = np.add.reduceat(local, start, axis=0)  # (V, 3) per-voxel sums
    second = np.add.reduceat(local[:, :, None] * local[:, None, :], start, axis=0)  # (V, 3, 3)
    total, total1, total2 = np.zeros(len(unique)), np.zeros_like(first), np.zeros_like(second)
    for offset in _NEIGHBOURS:  # the 27-voxel neighbourhood's moments, one offset at a time
        at = np.minimum(np.searchsorted(unique, unique + offset), len(unique) - 1)
        there = unique[at] == unique + offset
        total += np.where(there, count[at], 0)
        total1 += np.where(there[:, None], first[at], 0.0)
        total2 += np.where(there[:, None, None], second[at], 0.0)
    mean = total1 / total[:, None]
    covariance = total2 / total[:, None, None] - mean[:, :, None] * mean[:, None, :]
    values, vectors = np.linalg.eigh(covariance)  # ascending (V, 3), (V, 3, 3)
    linear = values[:, 1] <= _FLAT_RATIO * values[:, 2]
    planar = ~linear & (values[:, 0] <= _FLAT_RATIO * values[:, 1])
    shape = np.where(linear, LINEAR, np.where(planar, PLANAR, SCATTERED))
    shape[total < _SHAPE_MIN_POINTS] = SPARSE
    return VoxelIndex(voxel_m, points, voxel_of, unique, start, count, vectors[:, :, 0], shape)


def nearest_in_map(index: VoxelIndex, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest map point of each `(q, 3)` query within its 27 surrounding voxels: `(q,)` int64
    row of index.points (-1: none) and `(q,)` float64 squared distance (inf: none)."""
    nearest = np.full(len(queries), -1, np.int64)
    distance2 = np.full(len(queries), np.inf)
    for lo in range(0, len(queries), _QUERY_BLOCK):
        block = queries[lo : lo + _QUERY_BLOCK]
        wanted = voxel_keys(block, index.voxel_m)[:, None] + _NEIGHBOURS  # (b, 27)
        at = np.minimum(np.searchsorted(index.keys, wanted), len(index.keys) - 1)
        query, slot = np.nonzero(index.keys[at] == wanted)  # (pairs,) query-major
        voxel = at[query, slot]
        count = index.count[voxel]
        pair_query = np.repeat(query, count)  # (P,) ascending
        first = np.cumsum(count) - count
        row = np.repeat(index.start[voxel] - first, count) + np.arange(count.sum())  # (P,)
        if not len(row):
            continue
        offset = index.points[row] - block[pair_query]  # (P, 3)
        d2 = np.einsum("ij,ij->i", offset, offset)
        group = np.r_[0, np.flatnonzero(np.diff(pair_query)) + 1]  # (f,) first pair of a query
        found = pair_query[group]
        best = np.minimum.reduceat(d2, group)  # (f,)
        winners = np.flatnonzero(d2 == np.repeat(best, np.diff(np.r_[group, len(d2)])))
        first_winner = np.r_[0, np.flatnonzero(np.diff(pair_query[winners])) + 1]
        nearest[lo + found] = row[winners[first_winner]]
        distance2[lo + found] = best
    return nearest, distance2


# ---------------------------------------------------------------------------------------------
# ICP


def exp_se3(twist: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """`(4, 4)` rigid motion of `(6,)` twist (rotation vector rad, translation m) applied about
    `centre` `(3,)`: x -> R (x - centre) + centre + t."""
    angle = np.linalg.norm(twist[:3])
    axis = twist[:3] / angle if angle > 0 else np.zeros(3)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)
    motion = np.eye(4)
    motion[:3, :3] = rotation
    motion[:3, 3] = centre - rotation @ centre + twist[3:]
    return motion


def icp_step(
    source: np.ndarray, index: VoxelIndex, pose: np.ndarray, max_distance_m: float,
    kernel_m: float,
) -> np.ndarray | None:  # fmt: skip
    """One Gauss-Newton update `(6,)` (rotation vector, translation, about the pose's origin)
    of `pose` `(4, 4)` aligning `(s, 3)` scan points to the map (correspondences within
    `max_distance_m`, Geman-McClure scale `kernel_m`); None with fewer than 6 residuals."""
    world = source @ pose[:3, :3].T + pose[:3, 3]  # (s, 3)
    nearest, distance2 = nearest_in_map(index, world)
    keep = distance2 <= max_distance_m**2
    if keep.sum() < 6:
        return None
    p, q = world[keep], index.points[nearest[keep]]  # (k, 3) each
    voxel = index.voxel_of[nearest[keep]]
    shape, normal = index.shape[voxel], index.normals[voxel]
    planar, scattered = shape == PLANAR, shape == SCATTERED
    arm = p - pose[:3, 3]  # (k, 3) lever arms about the sensor: well conditioned far away
    kernel2 = kernel_m**2
    # point-to-plane rows: r = n . (p - q), dr/d(omega, t) = (arm x n, n)
    n, a = normal[planar], arm[planar]
    residual = np.einsum("ij,ij->i", n, p[planar] - q[planar])  # (k1,)
    jacobian = np.c_[np.cross(a, n), n]  # (k1, 6)
    weight = (kernel2 / (kernel2 + residual**2)) ** 2  # Geman-McClure
    hessian = jacobian.T @ (weight[:, None] * jacobian)
    gradient = jacobian.T @ (weight * residual)
    # point-to-point rows where the voxel is scattered: r = p - q, dr/d(omega, t) = (-[arm]x, I)
    a, r = arm[scattered], p[scattered] - q[scattered]  # (k2, 3)
    weight = (kernel2 / (kernel2 + (r**2).sum(axis=1))) ** 2  # (k2,)
    skew = np.zeros((len(a), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -a[:, 2], a[:, 1], -a[:, 0]
    skew = skew - skew.transpose(0, 2, 1)  # (k2, 3, 3) [arm]x
    rows = np.concatenate([-skew, np.broadcast_to(np.eye(3), skew.shape)], axis=2)  # (k2, 3, 6)
    hessian += np.einsum("k,kri,krj->ij", weight, rows, rows)
    gradient += np.einsum("k,kri,kr->i", weight, rows, r)
    hessian += 1e-9 * np.trace(hessian) * np.eye(6)  # a degenerate scene moves along nothing
    return -np.linalg.solve(hessian, gradient)


def align_scan(
    source: np.ndarray, index: VoxelIndex, initial: np.ndarray, params: RegistrationParams
) -> tuple[np.ndarray, int, bool]:
    """ICP of `(s, 3)` scan points to the map from `initial` `(4, 4)`: (pose `(4, 4)`,
    updates made, whether the last kernel's updates fell below the tolerance). The kernel
    starts at max_correspondence_m and halves at each convergence (an update below 10x the
    tolerance) down to kernel_m: a wide kernel first, so that a start a metre off (the second
    scan has no velocity yet) is not held by the residuals it makes."""
    pose = initial.copy()
    kernel = max(params.max_correspondence_m, params.kernel_m)
    for iteration in range(1, params.max_iterations + 1):
        twist = icp_step(source, index, pose, params.max_correspondence_m, kernel)
        if twist is None:
            return pose, iteration, False
        pose = exp_se3(twist, pose[:3, 3]) @ pose
        final = kernel <= params.kernel_m
        if np.abs(twist).sum() < params.tolerance * (1 if final else 10):
            if final:
                return pose, iteration, True
            kernel = max(kernel / 2, params.kernel_m)
    return pose, params.max_iterations, False


def register_scans(
    count: int,
    points_of: Callable[[int], np.ndarray],
    params: RegistrationParams = RegistrationParams(),
) -> Registration:
    """Poses of `count` scans in order, each `points_of(i)` `(n_i, >= 3)` in its LiDAR frame:
    scan 0 is the identity, scan i is aligned to the map of scans 0..i-1 from the constant
    velocity prediction. Deterministic. RegistrationError (naming the scan) when there are
    fewer than 2 scans, a scan holds NaN/inf, or keeps fewer than MIN_SCAN_POINTS points to
    register."""
    if count < 2:
        raise RegistrationError(0, f"{count} scan(s): registration needs at least 2")
    poses = np.tile(np.eye(4), (count, 1, 1))
    iterations = np.zeros(count, np.int64)
    converged = np.ones(count, bool)
    used = np.zeros(count, np.int64)
    map_points = np.zeros((0, 3))
    for i in range(count):
        points = np.asarray(points_of(i))
        if points.ndim != 2 or points.shape[1] < 3:
            raise RegistrationError(i, f"scan {i}: points of shape {points.shape}, not (n, >= 3)")
        if not np.isfinite(points[:, :3]).all():
            raise RegistrationError(i, f"scan {i}: points are NaN/inf")
        kept = voxel_downsample(crop_range(points, params.min_range_m, params.max_range_m),
                                0.5 * params.voxel_m)  # fmt: skip
        source = voxel_downsample(kept, 1.5 * params.voxel_m)
        used[i] = len(source)
        if len(source) < MIN_SCAN_POINTS:
            raise RegistrationError(
                i,
                f"scan {i}: {len(source)} points within {params.min_range_m:g}-"
                f"{params.max_range_m:g} m after thinning to {1.5 * params.voxel_m:g} m voxels, "
                f"fewer than the {MIN_SCAN_POINTS} registration needs",
            )
        if i > 0:
            last = poses[i - 1]
            step = np.eye(4)
            if params.motion_prior and i > 1:
                step = np.linalg.inv(poses[i - 2]) @ last  # (4, 4) the last motion, repeated
            index = index_map(map_points, params.voxel_m)
            poses[i], iterations[i], converged[i] = align_scan(source, index, last @ step, params)
        world = kept @ poses[i, :3, :3].T + poses[i, :3, 3]
        map_points = add_to_map(map_points, world, params.voxel_m, params.max_points_per_voxel)
        near = np.linalg.norm(map_points - poses[i, :3, 3], axis=1) <= params.max_range_m
        map_points = map_points[near]
    return Registration(poses, iterations, converged, used)
