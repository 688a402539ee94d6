"""Which true positives face backwards, by how the car is seen (not a test): every prediction
(score >= --score-min) matched to a labelled car at BEV IoU > 0.5, all difficulties; backwards
when its heading is more than 90 deg from the label's. Split by the labelled car's heading
against the sensor's ray (towards the sensor, away from it, sideways) and by range.

Usage:
  .venv/bin/python bench/backwards_by_view.py --gt LABELLED_FRAMESET PREDICTIONS.parquet ...
"""

from __future__ import annotations

import argparse

import numpy as np
import pyarrow.parquet as pq

from dali_cli.evaluation.errors import turned_around
from dali_cli.geometry import bev_iou, wrap_angle
from dali_cli.store.box_tables import BOX_FIELDS, read_boxes

RANGES_M = ((0, 20), (20, 40), (40, 80))


def matched(gt: np.ndarray, gt_frames, pred: np.ndarray, pred_frames) -> np.ndarray:
    """(range m, heading against the ray rad in [0, pi], backwards) `(M, 3)` of each label
    matched to its best-overlapping prediction of the frame (BEV IoU > 0.5)."""
    truths, partners = [], []
    for frame in np.unique(gt_frames):
        g, p = gt[gt_frames == frame], pred[pred_frames == frame]
        if not len(p):
            continue
        iou = bev_iou(g, p)
        best = iou.argmax(1)
        hit = iou[np.arange(len(g)), best] > 0.5
        truths.append(g[hit])
        partners.append(p[best[hit]])
    truth = np.concatenate(truths) if truths else np.zeros((0, 7))
    partner = np.concatenate(partners) if partners else np.zeros((0, 7))
    ray = np.arctan2(truth[:, 1], truth[:, 0])
    heading = np.abs(wrap_angle(truth[:, 6] - ray))
    return np.column_stack(
        [np.hypot(truth[:, 0], truth[:, 1]), heading, turned_around(partner, truth)]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gt", required=True)
    parser.add_argument("--score-min", type=float, default=0.3)
    parser.add_argument("predictions", nargs="+")
    args = parser.parse_args()
    labels = read_boxes(args.gt)
    for path in args.predictions:
        table = pq.read_table(path).to_pydict()
        keep = np.asarray(table["score"]) >= args.score_min
        pred = np.stack([np.asarray(table[f]) for f in BOX_FIELDS], 1)[keep]
        rows = matched(labels.boxes, np.asarray(labels["frame_id"]), pred,
                       np.asarray(table["frame_id"])[keep])  # fmt: skip
        distance, heading, back = rows[:, 0], rows[:, 1], rows[:, 2] > 0
        views = {
            "towards the sensor": heading > 3 * np.pi / 4,
            "away from it": heading < np.pi / 4,
            "sideways": (heading >= np.pi / 4) & (heading <= 3 * np.pi / 4),
        }
        views.update({f"{lo}-{hi} m": (distance >= lo) & (distance < hi) for lo, hi in RANGES_M})
        parts = ", ".join(f"{name} {back[m].sum()}/{m.sum()}" for name, m in views.items())
        print(f"{path}: backwards {back.sum()}/{len(back)}; {parts}")


if __name__ == "__main__":
    main()
