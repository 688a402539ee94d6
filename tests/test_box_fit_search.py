"""The pruned pose search of the point fit (dali_cli.labels.box_fit.best_pose): the very pose a
straightforward exhaustive search of every pose on every point picks (the fit's float32
arithmetic, float64 sums, the unmoved pose winning ties, then the first), on random point
sets, on sets where most poses tie, and on cars seen on their faces with ground and a
neighbour; its block bounds never exceed a cost of their block."""

from __future__ import annotations

import numpy as np
import pytest
from test_box_fit import car, ground, moved, near_faces

from dali_cli.labels.box_fit import PointFit, candidate_points, fit_boxes
from dali_cli.labels.pose_search import (
    PRUNE_BLOCKS,
    best_pose,
    block_lower_bounds,
    pose_blocks,
    pose_costs,
    unmoved_pose,
)

SMALL = PointFit(along_m=0.4, across_m=0.1, turn_deg=3.0)  # 17 x 9 shifts x 7 turns


def exhaustive_costs(uv: np.ndarray, half_lw: np.ndarray, fit: PointFit) -> np.ndarray:
    """Every pose's cost `(G,)`, all poses in one broadcast `(D, T, n)` (the per-box reference:
    points turned, shift turned, subtracted; float32 elementwise, float64 sums)."""
    shifts, turns = fit.axes()
    cos, sin = np.cos(turns).astype(np.float32), np.sin(turns).astype(np.float32)
    u, v = np.asarray(uv, np.float32).T
    along = (cos[:, None] * u + sin[:, None] * v)[None]  # (1, T, n)
    across = (-sin[:, None] * u + cos[:, None] * v)[None]
    du, dv = shifts.astype(np.float32).T
    a = np.abs(along - (cos * du[:, None] + sin * dv[:, None])[..., None])  # (D, T, n)
    b = np.abs(across - (-sin * du[:, None] + cos * dv[:, None])[..., None])
    half_l, half_w = np.float32(half_lw[0]), np.float32(half_lw[1])
    side = np.clip(np.minimum(half_l - a, half_w - b), 0, np.float32(fit.side_cap_m)) ** 2
    out = (np.maximum(a - half_l, 0) + np.maximum(b - half_w, 0)) ** 2
    total = side.sum(-1, dtype=np.float64) + fit.outside_weight * out.sum(-1, dtype=np.float64)
    return total.reshape(-1)


def exhaustive_pose(uv: np.ndarray, half_lw: np.ndarray, fit: PointFit) -> int:
    costs = exhaustive_costs(uv, half_lw, fit)
    zero = unmoved_pose(fit)
    return zero if costs[zero] <= costs.min() else int(np.argmin(costs))


def random_case(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A box's half length and width `(2,)` and points `(n, 2)` in its frame: a car's two near
    faces (noisy, the car off the box by up to 0.6 m and 6 degrees) and clutter about it."""
    rng = np.random.default_rng(seed)
    half = np.array([rng.uniform(1.4, 2.6), rng.uniform(0.6, 1.1)])
    n = int(rng.integers(10, 400))
    faces = int(rng.integers(0, n + 1))
    t = rng.uniform(-1, 1, faces)
    on_end = rng.random(faces) < 0.4
    face = np.where(
        on_end[:, None],
        np.c_[np.full(faces, -half[0]), t * half[1]],
        np.c_[t * half[0], np.full(faces, half[1])],
    ) + rng.normal(0, rng.uniform(0.005, 0.1), (faces, 2))
    turn = np.radians(rng.uniform(-6, 6))
    rotation = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    face = face @ rotation.T + rng.uniform([-0.6, -0.2], [0.6, 0.2])
    clutter = rng.uniform(-(half + 0.6), half + 0.6, (n - faces, 2))
    return half, np.concatenate([face, clutter])


@pytest.mark.parametrize("fit", [PointFit(), SMALL], ids=["default", "small"])
@pytest.mark.parametrize("seed", range(12))
def test_best_pose_is_the_exhaustive_winner_on_random_points(fit, seed):
    half, uv = random_case(seed)
    assert best_pose(uv, half, fit) == exhaustive_pose(uv, half, fit)


def test_pose_costs_of_any_pose_subset_are_the_exhaustive_costs_bit_for_bit():
    half, uv = random_case(99)
    expected = exhaustive_costs(uv, half, SMALL)
    poses = np.random.default_rng(0).permutation(len(expected))[:200]
    np.testing.assert_array_equal(pose_costs(uv, half, SMALL, poses, chunk=333), expected[poses])
    np.testing.assert_array_equal(pose_costs(uv, half, SMALL), expected)


def test_when_poses_tie_the_unmoved_pose_wins_then_the_first():
    half = np.array([1.95, 1.0])
    rng = np.random.default_rng(3)
    inside = rng.uniform(-0.1, 0.1, (40, 2))  # > 0.5 m from every side of every pose: all tie
    assert exhaustive_pose(inside, half, PointFit()) == unmoved_pose(PointFit())
    assert best_pose(inside, half, PointFit()) == unmoved_pose(PointFit())
    # points 0.25 m ahead of a box 4 m long, on a line across it: the 17 poses shifted 0.25 m
    # forward, unturned, put them exactly on the front face (cost 0, float32-exact); the unmoved
    # pose leaves them outside: the winner is the first of the 17 (the largest shift to the right)
    face = np.c_[np.full(30, 2.25), np.linspace(-0.3, 0.3, 30)]
    fit = PointFit()
    costs = exhaustive_costs(face, np.array([2.0, 1.0]), fit)
    tied = np.flatnonzero(costs == 0)
    assert len(tied) == 17 and np.allclose(fit.grid()[tied, 0], 0.25)
    assert best_pose(face, np.array([2.0, 1.0]), fit) == tied[0]


@pytest.mark.parametrize("seed", range(4))
def test_block_bounds_never_exceed_a_cost_of_their_block(seed):
    half, uv = random_case(100 + seed)
    costs = exhaustive_costs(uv, half, PointFit())
    for block in PRUNE_BLOCKS:
        pose_block, ranges = pose_blocks(PointFit(), block)
        blocks = np.arange(ranges.shape[1])
        bounds = block_lower_bounds(uv, half, PointFit(), block, blocks)
        least = np.full(len(blocks), np.inf)
        np.minimum.at(least, pose_block, costs)
        assert (bounds <= least).all()
        assert (bounds > 0.5 * least).mean() > 0.2  # and they bound: most are not trivial
        every = block_lower_bounds(uv, half, PointFit(), block, None)  # the broadcast path
        np.testing.assert_allclose(every, bounds, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_fit_boxes_equals_the_per_box_exhaustive_fit_on_cars_and_ground(seed):
    rng = np.random.default_rng(seed)
    truths = [car(rng.uniform(8, 30), rng.uniform(-8, 8), rng.uniform(-3, 3)) for _ in range(3)]
    truths.append(moved(truths[0], 4.6, 0.2, 4.0))  # a neighbour just ahead of the first
    points = np.concatenate(
        [near_faces(t, per_face=int(rng.integers(5, 120)), seed=seed + i) for i, t in
         enumerate(truths)] + [ground(seed)]
    )  # fmt: skip
    starts = np.stack([moved(t, *rng.uniform([-0.5, -0.15, -6], [0.5, 0.15, 6])) for t in truths])
    fit = PointFit()
    fitted, used = fit_boxes(starts, points, fit)
    grid = fit.grid()
    for k, uv in enumerate(candidate_points(starts, points, fit)):
        assert used[k] == len(uv)
        if len(uv) < fit.min_points:
            np.testing.assert_array_equal(fitted[k], starts[k])
            continue
        du, dv, turn = grid[exhaustive_pose(uv, starts[k, 3:5] / 2, fit)]
        c, s = np.cos(starts[k, 6]), np.sin(starts[k, 6])
        expected = starts[k].copy()
        expected[0] += c * du - s * dv
        expected[1] += s * du + c * dv
        assert fitted[k, 0] == expected[0] and fitted[k, 1] == expected[1]
        assert np.cos(fitted[k, 6] - starts[k, 6] - turn) > 1 - 1e-12
