"""How finely AP_3D@0.7 resolves a size change at 200 validation frames.

For RUN/baselines/source_<budget>_budget (its saved eval_ptsn predictions): AP_3D @0.7 (range
protocol, front region; all and 0-30 / 30-50 / 50-80 m) with one dimension of every predicted car
multiplied by k (bottom face kept, as `dali eval --size-correction per-dim`), and the predictions
with score >= 0.5 whose best 3D IoU with a true car crosses 0.7 between k = 1 and each k.

  PYTHONPATH=. .venv/bin/python docs/results/exp600/size_sensitivity.py RUN [x1|x2] [l|w|h]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from dali_cli.evaluation.evaluate import evaluate
from dali_cli.importers.kitti_label import read_box_source
from dali_cli.geometry import iou_3d
from stages.eval import resized

FACTORS = (0.99, 0.995, 0.998, 1.0, 1.002, 1.005, 1.01)


def best_iou(pred, gt) -> np.ndarray:
    """(N,) the best 3D IoU of each Car prediction with a true Car of its frame (0 if none)."""
    best = np.zeros(len(pred))
    gt_frames = gt.rows_by_frame()
    for frame, rows in pred.rows_by_frame().items():
        truth = gt_frames.get(frame)
        if truth is not None and len(truth):
            best[rows] = iou_3d(pred.boxes[rows], gt.boxes[truth]).max(axis=1)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("budget", choices=["x1", "x2"], nargs="?", default="x2")
    parser.add_argument("dimension", choices=["l", "w", "h"], nargs="?", default="h")
    args = parser.parse_args()
    control = args.run / f"baselines/source_{args.budget}_budget"
    pred, _ = read_box_source(control / "eval_ptsn/predictions.parquet", "pred")
    gt, _ = read_box_source(args.run / "data/target_val", "gt")
    cars = np.asarray(gt["label"]).astype(str) == "Car"
    gt = gt.select(np.flatnonzero(cars))
    pred = pred.select(np.flatnonzero(np.asarray(pred["label"]).astype(str) == "Car"))
    base = best_iou(pred, gt)
    confident = np.asarray(pred["score"]) >= 0.5
    print(f"{control}: dimension {args.dimension} x k (bottom face kept)")
    for k in FACTORS:
        factors = np.ones(3)
        factors["lwh".index(args.dimension)] = k
        changed = resized(pred, factors, "Car")
        ap = evaluate(changed, gt, iou=0.7, protocol="range", front_only=True)["Car"]["3d"]
        after = best_iou(changed, gt)
        lost = confident & (base > 0.7) & (after <= 0.7)
        won = confident & (base <= 0.7) & (after > 0.7)
        bands = " / ".join(f"{ap[b]:.1f}" for b in ("0-30", "30-50", "50-80"))
        print(f"  k {k:<6} AP_3D {ap['all']:6.2f} ({bands})  boxes (score >= 0.5) crossing 0.7: "
              f"{int(lost.sum())} lost, {int(won.sum())} gained")  # fmt: skip


if __name__ == "__main__":
    main()
