"""Label-free: how far the x2-budget control's boxes sit above the local ground.

For the first 100 validation frames of RUN: per box (predictions at score >= 0.5 of
RUN/baselines/source_x2_budget/eval_ptsn, and, as the estimator's check, the true cars), the box
bottom minus the 20th percentile z of the points in a 1 m ring around its footprint (within 1 m of
its bottom in z). The predictions need no label; the true cars only check the estimator.

  PYTHONPATH=. .venv/bin/python docs/results/exp600/ground_offset.py RUN
"""

import sys
from pathlib import Path

import numpy as np

from dali_cli.importers.kitti_label import read_box_source as read_table
from dali_cli.store.artifacts import FrameSet


def offsets(boxes, points, ring=1.0, pct=20):
    out = []
    for b in boxes:
        x, y, z, l, w, h, yaw = b[:7]
        c, s = np.cos(yaw), np.sin(yaw)
        dx, dy = points[:, 0] - x, points[:, 1] - y
        u, v = c * dx + s * dy, -s * dx + c * dy
        near = (np.abs(u) < l / 2 + ring) & (np.abs(v) < w / 2 + ring)
        inside = (np.abs(u) < l / 2 + 0.1) & (np.abs(v) < w / 2 + 0.1)
        zs = points[near & ~inside & (np.abs(points[:, 2] - (z - h / 2)) < 1.0), 2]
        if len(zs) < 5:
            continue
        out.append((z - h / 2) - np.percentile(zs, pct))
    return np.array(out)

run = Path(sys.argv[1])
pred, _ = read_table(run / "baselines/source_x2_budget/eval_ptsn/predictions.parquet", "pred")
gt, _ = read_table(run / "data/target_val", "gt")
frames = FrameSet(run / "data/target_val")
pf, S = np.asarray(pred.frame_id), np.asarray(pred["score"])
gf, gl = np.asarray(gt.frame_id), np.asarray(gt["label"]).astype(str)
po, go = [], []
for fid in frames.frame_ids[:100]:
    pts = frames.frame(fid)
    po.append(offsets(pred.boxes[(pf == fid) & (S >= 0.5)], pts))
    go.append(offsets(gt.boxes[(gf == fid) & (gl == "Car")], pts))
po, go = np.concatenate(po), np.concatenate(go)
print(run.name, f"pred bottom - local ground: mean {po.mean():+.3f} median {np.median(po):+.3f} (n={len(po)}); true cars: mean {go.mean():+.3f} median {np.median(go):+.3f} (n={len(go)})")
