"""Where the per-dimension size correction of an equal-budget control gains or loses.

For RUN/baselines/source_<budget>_budget: AP_3D / AP_BEV @0.7 (range protocol, front region) of its
saved eval_ptsn predictions with each dimension's factor E_est / E_pred(ŝ) of its own sweep applied
alone, then l+w, then all three (bottom face kept, as `dali eval --size-correction per-dim`); and
the mean size and bottom/top z offset of the predictions (score >= 0.3) whose centre lies within
0.5 m of a true car's, against those cars.

  PYTHONPATH=. .venv/bin/python docs/results/exp600/size_correction_dims.py RUN [x1|x2]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from dali_cli.evaluation.evaluate import evaluate
from dali_cli.importers.kitti_label import read_box_source as read_table
from stages.eval import resized

DIMENSIONS = {"none": (0, 0, 0), "l": (1, 0, 0), "w": (0, 1, 0), "h": (0, 0, 1),
              "l,w": (1, 1, 0), "l,w,h": (1, 1, 1)}  # fmt: skip


def matched_pairs(pred, gt, score_min: float = 0.3, radius_m: float = 0.5):
    """(pred boxes (M, 7), true boxes (M, 7)): per true car, the nearest prediction in BEV with
    score >= score_min when its centre lies within radius_m."""
    keep = np.asarray(pred["score"]) >= score_min
    boxes, frames = pred.boxes[keep], np.asarray(pred.frame_id)[keep]
    cars = np.asarray(gt["label"]).astype(str) == "Car"
    truth, truth_frames = gt.boxes[cars], np.asarray(gt.frame_id)[cars]
    found, true = [], []
    for frame in np.unique(truth_frames):
        p, g = boxes[frames == frame], truth[truth_frames == frame]
        if len(p) == 0:
            continue
        distance = np.linalg.norm(p[:, None, :2] - g[None, :, :2], axis=2)  # (P, G)
        nearest = distance.argmin(axis=0)
        close = distance[nearest, np.arange(len(g))] < radius_m
        found.append(p[nearest[close]])
        true.append(g[close])
    return np.concatenate(found), np.concatenate(true)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("budget", choices=("x1", "x2"))
    args = parser.parse_args()
    control = args.run / f"baselines/source_{args.budget}_budget"
    pred, _ = read_table(control / "eval_ptsn/predictions.parquet", "pred")
    gt, frames = read_table(args.run / "data/target_val", "gt")
    sweep = json.loads((control / "ptsn/scale.json").read_text())
    factors = np.array(sweep["E_est"]) / np.array(sweep["E_pred_at_scale"])
    print(f"{control}: factors l/w/h {np.round(factors, 3).tolist()}")
    for name, mask in DIMENSIONS.items():
        applied = np.where(np.array(mask, bool), factors, 1.0)
        block = evaluate(
            resized(pred, applied, "Car"), gt, iou=0.7, recall_positions=40, protocol="range",
            class_name="Car", min_gt_points=0, frame_ids=frames, front_only=True,
        )["Car"]  # fmt: skip
        bands = " / ".join(f"{block['3d'][b]:.1f}" for b in ("0-30", "30-50", "50-80"))
        print(f"  corrected {name:6s} AP_3D {block['3d']['all']:.2f} ({bands})  "
              f"AP_BEV {block['bev']['all']:.2f}")  # fmt: skip
    found, true = matched_pairs(pred, gt)
    bottom = (found[:, 2] - found[:, 5] / 2) - (true[:, 2] - true[:, 5] / 2)
    top = (found[:, 2] + found[:, 5] / 2) - (true[:, 2] + true[:, 5] / 2)
    keep = np.asarray(pred["score"]) >= 0.3
    print(f"  {len(found)} matched of {keep.sum()} predictions >= 0.3: mean l/w/h "
          f"{np.round(found[:, 3:6].mean(0), 3).tolist()} vs truth "
          f"{np.round(true[:, 3:6].mean(0), 3).tolist()}; all predictions "
          f"{np.round(pred.boxes[keep][:, 3:6].mean(0), 3).tolist()}; bottom z {bottom.mean():+.3f} m, "
          f"top z {top.mean():+.3f} m")  # fmt: skip


if __name__ == "__main__":
    main()
