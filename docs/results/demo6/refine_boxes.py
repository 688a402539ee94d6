"""Prototype (session 12; not a DALI stage yet): move each pseudo box to fit its points, using the
target points only (no label). For every box, the points in the box grown by 0.6 m (above its
bottom + 0.2 m, so no ground) are scored against candidate boxes of the same size shifted by
-0.6..0.6 m along the box, -0.2..0.2 m across and turned by -4..4 degrees: cost = sum over points of
min(distance to the nearest side, 0.5 m)^2 + 10 x (distance outside the box)^2, so the sides hug
the visible faces and every point stays inside. Boxes with fewer than 10 such points are kept.

    python docs/results/demo6/refine_boxes.py --target RUN/data/target --pseudo RUN/iter1/pseudo --out DIR
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))

from dali_cli.geometry import count_points_in_boxes, wrap_angle  # noqa: E402
from dali_cli.store.artifacts import BoxTable, FrameSet, read_boxes, write_boxes  # noqa: E402

SHIFTS_ALONG = np.arange(-0.6, 0.601, 0.05)
SHIFTS_ACROSS = np.arange(-0.2, 0.201, 0.025)
TURNS = np.radians(np.arange(-4.0, 4.01, 1.0))
GRID = np.stack(np.meshgrid(SHIFTS_ALONG, SHIFTS_ACROSS, TURNS, indexing="ij"), -1).reshape(-1, 3)


def refine(box: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The box (7,) moved and turned to fit `points` (n, >=3); unchanged when too few points."""
    c, s = np.cos(box[6]), np.sin(box[6])
    rel = points[:, :2] - box[:2]
    u, v = c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]
    half_l, half_w, bottom = box[3] / 2, box[4] / 2, box[2] - box[5] / 2
    near = (np.abs(u) < half_l + 0.6) & (np.abs(v) < half_w + 0.6)
    near &= (points[:, 2] > bottom + 0.2) & (points[:, 2] < bottom + box[5] + 0.3)
    u, v = u[near], v[near]
    if len(u) < 10:
        return box
    du, dv, turn = GRID[:, 0:1], GRID[:, 1:2], GRID[:, 2:3]  # (G, 1)
    a = np.cos(turn) * (u - du) + np.sin(turn) * (v - dv)  # (G, n)
    b = -np.sin(turn) * (u - du) + np.cos(turn) * (v - dv)
    outside = np.maximum(np.abs(a) - half_l, 0) + np.maximum(np.abs(b) - half_w, 0)
    side = np.minimum(half_l - np.abs(a), half_w - np.abs(b)).clip(0, 0.5)
    best = int(np.argmin((side**2).sum(1) + 10 * (outside**2).sum(1)))
    du, dv, turn = GRID[best]
    moved = box.copy()
    moved[0] += c * du - s * dv
    moved[1] += s * du + c * dv
    moved[6] = wrap_angle(box[6] + turn)
    return moved


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--target", type=Path, required=True)
    parser.add_argument("--pseudo", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    pseudo = read_boxes(args.pseudo)
    rows = pseudo.rows_by_frame()
    boxes, counts = pseudo.boxes.copy(), np.zeros(len(pseudo), np.int32)
    for frame_id, points in FrameSet(args.target).iter_frames():
        if frame_id in rows:
            r = rows[frame_id]
            boxes[r] = np.array([refine(box, points) for box in pseudo.boxes[r]]).reshape(-1, 7)
            counts[r] = count_points_in_boxes(points, boxes[r])
    out = BoxTable.from_arrays(pseudo.frame_id, boxes, score=pseudo["score"], num_points=counts)
    args.out.mkdir(parents=True, exist_ok=True)
    write_boxes(args.out, out)
    moved = np.hypot(*(boxes[:, :2] - pseudo.boxes[:, :2]).T)
    record = {"command": " ".join(sys.argv), "boxes": len(out), "mean_shift_m": float(moved.mean())}
    (args.out / "refined.json").write_text(json.dumps(record, indent=2) + "\n")
    print(json.dumps(record))


if __name__ == "__main__":
    main()
