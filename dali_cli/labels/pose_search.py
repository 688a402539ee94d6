"""The pose search of the point fit (dali_cli.labels.box_fit): the cost of a box's candidate
poses on its points, and the cheapest pose found by branch and bound over blocks of the grid
(bounded from below, most never scored) -- the very pose the exhaustive search of every pose on
every point picks, bit for bit (tests/test_box_fit_search.py). On drive 0001's 2,773 pseudo
boxes the fitted boxes are bitwise those of the exhaustive search, in a fraction of its time
(docs/ptsn.md, "Speed: pseudo-label against `dali detect`"; bench/pose_search_speed.py).

Poses: the grid of PointFit.grid(), pose g = shift g // T turned by turn g % T. Lengths in
metres, turns in radians.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from dali_cli.labels.point_fit import PointFit

PRUNE_BLOCKS = ((8, 17), (4, 6), (2, 2))  # best_pose's blocks (along x across steps, one turn each)
BOUND_RELATIVE, BOUND_PER_POINT = 1e-3, 1e-5  # block_lower_bounds' allowance for float32 rounding


@lru_cache(maxsize=8)
def unmoved_pose(fit: PointFit) -> int:
    """The index of the zero offset in fit.grid() (it wins ties)."""
    return int(np.argmin(np.abs(fit.grid()).sum(1)))


def pose_costs(
    uv: np.ndarray,
    half_lw: np.ndarray,
    fit: PointFit,
    poses: np.ndarray | None = None,
    chunk: int = 65536,
    turned: tuple[np.ndarray, ...] | None = None,
) -> np.ndarray:
    """The cost of poses of `fit.grid()` `(P,)` float64 (`poses`: their indices `(P,)` into the
    grid, ascending or not; default every pose) for one box's points `uv (n, 2)` (its frame, m)
    and half length and width `(2,)` m.

    A point's coordinates in the box shifted by (du, dv) and turned by t are its coordinates
    turned by t minus the shift turned by t, so the points are turned once per turn `(T, n)`
    and each pose only subtracts; float32 elementwise, each pose's sums over its points in
    float64 (one contiguous row of n per pose: a pose's cost does not depend on which other
    poses are scored with it, nor on `chunk`), about `chunk` elements at a time (the work stays
    in cache). `turned`: _turned(uv, fit) when already made."""
    a0, b0, shift_a, shift_b = turned or _turned(uv, fit)  # (T, n), (D, T)
    half_l, half_w = (np.float32(x) for x in half_lw)
    cap = np.float32(fit.side_cap_m)
    poses = np.arange(shift_a.size) if poses is None else np.asarray(poses, np.int64)
    shift, turn = np.divmod(poses, len(a0))  # (P,) each
    costs = np.empty(len(poses), np.float64)
    step = max(1, chunk // max(a0.shape[1], 1))
    for s in range(0, len(poses), step):
        d, t = shift[s : s + step], turn[s : s + step]
        a = np.abs(a0[t] - shift_a[d, t, None])  # (p, n)
        b = np.abs(b0[t] - shift_b[d, t, None])
        side = np.minimum(half_l - a, half_w - b)
        np.maximum(side, 0, out=side)  # clip to [0, cap], without np.clip's overhead
        np.minimum(side, cap, out=side)
        side *= side
        a -= half_l  # a, b become the distances outside the box along and across
        np.maximum(a, 0, out=a)
        b -= half_w
        np.maximum(b, 0, out=b)
        a += b
        a *= a
        costs[s : s + step] = side.sum(-1, dtype=np.float64) + fit.outside_weight * a.sum(
            -1, dtype=np.float64
        )
    return costs


@lru_cache(maxsize=8)
def turned_shifts(fit: PointFit) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What of the cost does not depend on the points, made once per fit (read only): the
    turns' cos and sin `(T,)` float32 and each shift turned by each turn `shift_a, shift_b
    (D, T)` float32 (m, along and across the turned box)."""
    shifts, turns = fit.axes()
    cos, sin = np.cos(turns).astype(np.float32), np.sin(turns).astype(np.float32)  # (T,)
    du, dv = (shifts[:, i, None].astype(np.float32) for i in (0, 1))  # (D, 1)
    made = cos, sin, cos * du + sin * dv, -sin * du + cos * dv
    for array in made:
        array.flags.writeable = False
    return made


def _turned(uv: np.ndarray, fit: PointFit) -> tuple[np.ndarray, ...]:
    """The float32 quantities every pose's cost is made of: the points turned by each turn
    `a0, b0 (T, n)` (m, along and across the turned box) and each shift turned by each turn
    `shift_a, shift_b (D, T)` (m, turned_shifts)."""
    cos, sin, shift_a, shift_b = turned_shifts(fit)
    u, v = (np.asarray(uv, np.float32)[:, i] for i in (0, 1))
    a0 = cos[:, None] * u + sin[:, None] * v  # (T, n): along the turned box, unshifted
    b0 = -sin[:, None] * u + cos[:, None] * v
    return a0, b0, shift_a, shift_b


@lru_cache(maxsize=8)
def pose_blocks(fit: PointFit, block: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The grid cut into blocks: for each turn, the shifts in blocks of `block` = (along,
    across) consecutive grid steps (the last block of an axis may be short). Returns each pose's
    block `(G,)` int64 (block = shift block * T + turn) and each block's range of turned shifts
    `(4, B)` float32: lowest and highest shift_a, lowest and highest shift_b (turned_shifts)."""
    shifts, turns = fit.axes()
    along = int(np.unique(shifts[:, 0]).size)
    steps = (along, len(shifts) // along)
    counts = [-(-n // b) for n, b in zip(steps, block, strict=True)]  # blocks per axis
    index = np.arange(len(shifts)).reshape(steps)  # (along, across) -> shift index
    padded = np.pad(
        index, [(0, c * b - n) for c, b, n in zip(counts, block, steps, strict=True)], mode="edge"
    )  # fmt: skip  (a short block repeats its last shift)
    members = padded.reshape(counts[0], block[0], counts[1], block[1]).transpose(0, 2, 1, 3)
    members = members.reshape(counts[0] * counts[1], -1)  # (shift blocks, block size)
    shift_block = np.empty(len(shifts), np.int64)
    shift_block[members] = np.arange(len(members))[:, None]
    pose_block = (shift_block[:, None] * len(turns) + np.arange(len(turns))).reshape(-1)
    _, _, shift_a, shift_b = turned_shifts(fit)
    ranges = np.stack(
        [f(values[members], axis=1).reshape(-1) for values in (shift_a, shift_b)
         for f in (np.min, np.max)]
    )  # fmt: skip
    for array in (pose_block, ranges):
        array.flags.writeable = False
    return pose_block, ranges


def block_lower_bounds(
    uv: np.ndarray,
    half_lw: np.ndarray,
    fit: PointFit,
    block: tuple[int, int],
    blocks: np.ndarray | None,
    turned: tuple[np.ndarray, ...] | None = None,
) -> np.ndarray:
    """A lower bound of pose_costs over each of `blocks` `(B,)` (indices into
    pose_blocks(fit, block); None: every block) `(B,)` float64, no larger than the cost of any
    pose of the block (uv `(n, 2)` m, half_lw `(2,)` m).

    Over a block a point's a and b (pose_costs, before |.|) lie in intervals: the turned point
    less the block's range of turned shifts, centre c and half width r. With d = |c|, the
    largest |a| over the block is d + r and the smallest max(d - r, 0); a point's cost is least
    on the box's boundary (0) when the intervals reach it, else at their corner nearest it:
    inside, the largest |a|, |b|; outside, the smallest. Made from pose_costs' own float32
    inputs in float32, then lowered by BOUND_RELATIVE and BOUND_PER_POINT per point to cover
    the float32 rounding of both. `turned`: as pose_costs'."""
    a0, b0 = (turned or _turned(uv, fit))[:2]  # (T, n) each
    middle, radius = block_intervals(fit, block)  # (2, B) each
    n_turns = len(a0)
    half = np.asarray(half_lw, np.float32)
    side = outside = None
    for axis, centre in enumerate((a0, b0)):
        if blocks is None:  # every block: block = shift block * T + turn, no gather needed
            mid = middle[axis].reshape(-1, n_turns, 1)
            d = np.abs(centre - mid).reshape(-1, centre.shape[1])  # (B, n)
            r = radius[axis, :, None]
        else:
            d = np.abs(centre[blocks % n_turns] - middle[axis, blocks, None])
            r = radius[axis, blocks, None]
        inside = (half[axis] - r) - d  # half - the largest |a| (|b|)
        d -= r + half[axis]  # the smallest |a| (|b|) outside the box, where positive
        np.maximum(d, 0, out=d)
        if side is None:
            side, outside = inside, d
        else:
            np.minimum(side, inside, out=side)
            outside += d
    np.maximum(side, 0, out=side)
    np.minimum(side, np.float32(fit.side_cap_m), out=side)
    bound = np.einsum("ij,ij->i", side, side).astype(np.float64)
    bound += fit.outside_weight * np.einsum("ij,ij->i", outside, outside)
    return bound * (1 - BOUND_RELATIVE) - BOUND_PER_POINT * len(uv)


@lru_cache(maxsize=8)
def block_intervals(fit: PointFit, block: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Each block's range of turned shifts (pose_blocks) as middle and half width `(2, B)`
    float32 each (along, across; read only), the half width grown by a part in 10^6 so that
    the float32 middle +- half width still covers the range."""
    ranges = pose_blocks(fit, block)[1]
    middle = (ranges[[0, 2]] + ranges[[1, 3]]) / 2
    radius = (ranges[[1, 3]] - ranges[[0, 2]]) / 2 * np.float32(1 + 1e-6)
    made = middle.astype(np.float32), radius.astype(np.float32)
    for array in made:
        array.flags.writeable = False
    return made


def best_pose(uv: np.ndarray, half_lw: np.ndarray, fit: PointFit) -> int:
    """The index into `fit.grid()` of the cheapest pose of `pose_costs` for one box's points
    `uv (n, 2)` and half length and width `(2,)`: the unmoved pose when no pose is cheaper,
    else the first cheapest -- exactly the pose the exhaustive search of every pose picks,
    found by scoring only the poses of the blocks that may hold it.

    Branch and bound over PRUNE_BLOCKS (coarse, then fine): the live blocks are bounded from
    below (block_lower_bounds), every pose of the lowest-bound block is scored, and a block
    whose bound exceeds the cheapest pose scored so far (these and the unmoved pose) cannot hold
    the winner and is dropped. The surviving poses are scored with the same float32 arithmetic
    and float64 sums as the exhaustive search (pose_costs): the same costs, bit for bit, so
    the same winner, ties broken the same way."""
    zero, turned = unmoved_pose(fit), _turned(uv, fit)
    alive, bound = None, np.inf  # alive: the poses still in the race (None: every pose)
    for block in PRUNE_BLOCKS:
        pose_block, ranges = pose_blocks(fit, block)
        if alive is None:
            alive, blocks, of_pose = np.arange(len(pose_block)), None, pose_block
        else:
            live = np.zeros(ranges.shape[1], bool)
            live[pose_block[alive]] = True
            blocks = np.flatnonzero(live)  # the live blocks, ascending
            of_pose = (np.cumsum(live) - 1)[pose_block[alive]]  # each pose's place in blocks
        bounds = block_lower_bounds(uv, half_lw, fit, block, blocks, turned)
        probes = np.append(alive[of_pose == np.argmin(bounds)], zero)
        bound = min(bound, pose_costs(uv, half_lw, fit, probes, turned=turned).min())
        alive = alive[bounds[of_pose] <= bound]
    costs = pose_costs(uv, half_lw, fit, alive, turned=turned)
    at_zero = np.flatnonzero(alive == zero)
    if len(at_zero) and costs[at_zero[0]] <= costs.min():
        return zero
    return int(alive[np.argmin(costs)])  # ascending: the first cheapest
