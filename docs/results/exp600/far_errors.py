"""Where the oracle's 3D lead on far cars comes from.

For each row's saved predictions (eval predictions.parquet) against the validation labels: every
true Car in the evaluation's front region (90 deg), per range band, paired with the prediction of
score >= --score-min of its frame with the highest BEV IoU (> 0.3). Printed per band: how many
true cars some prediction finds at 3D IoU >= 0.7; how many the paired one finds at BEV IoU >= 0.7;
over those BEV-found pairs, the median absolute error of the box centre along the sensor ray
(radial), across it, in z, of l / w / h and of yaw, and the mean signed error in z and h
(prediction minus truth, m).

  PYTHONPATH=. .venv/bin/python docs/results/exp600/far_errors.py GT_DIR name=PRED.parquet ...
"""

from __future__ import annotations

import argparse

import numpy as np

from dali_cli.evaluation.evaluate import in_st3d_region
from dali_cli.importers.kitti_label import read_box_source
from dali_cli.geometry import bev_iou, iou_3d, wrap_angle

BANDS = ((0, 30), (30, 50), (50, 80))


def median_abs(values: np.ndarray) -> str:
    return f"{np.median(np.abs(values)):.3f}"


def cars(table):
    return table.select(np.flatnonzero(np.asarray(table["label"]).astype(str) == "Car"))


def pairs(pred, gt, score_min: float):
    """(true boxes (M, 7), paired prediction (M, 7) or NaN, its BEV IoU (M,), its 3D IoU (M,),
    the best 3D IoU of any prediction (M,))."""
    keep = np.asarray(pred["score"]) >= score_min
    pred = pred.select(np.flatnonzero(keep))
    pred_frames = pred.rows_by_frame()
    truth, match, bev, iou3, any3 = [], [], [], [], []
    for frame, rows in gt.rows_by_frame().items():
        boxes = gt.boxes[rows]
        truth.append(boxes)
        found = np.full((len(rows), 7), np.nan)
        b = np.zeros(len(rows))
        t = np.zeros(len(rows))
        a = np.zeros(len(rows))
        cand = pred_frames.get(frame)
        if cand is not None and len(cand):
            ious = bev_iou(boxes, pred.boxes[cand])  # (M, K)
            best = ious.argmax(axis=1)
            b = ious[np.arange(len(rows)), best]
            ok = b > 0.3
            found[ok] = pred.boxes[cand][best[ok]]
            overlap = iou_3d(boxes, pred.boxes[cand])  # (M, K), once per frame
            t[ok] = overlap[np.flatnonzero(ok), best[ok]]
            b[~ok] = 0.0
            a = overlap.max(axis=1)
        any3.append(a)
        match.append(found)
        bev.append(b)
        iou3.append(t)
    return tuple(np.concatenate(v) for v in (truth, match, bev, iou3, any3))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("gt")
    parser.add_argument("rows", nargs="+", help="name=predictions.parquet")
    parser.add_argument("--score-min", type=float, default=0.5)
    args = parser.parse_args()
    gt, _ = read_box_source(args.gt, "gt")
    gt = cars(gt)
    gt = gt.select(np.flatnonzero(in_st3d_region(gt)))  # the evaluation's front region
    print(
        "| row | band m | true cars | 3D IoU >= 0.7 | BEV IoU >= 0.7 | radial | across | |dz| "
        "| |dl| | |dw| | |dh| | |dyaw| deg | mean dz | mean dh |"
    )
    print("|---" * 14 + "|")
    for spec in args.rows:
        name, path = spec.split("=", 1)
        pred, _ = read_box_source(path, "pred")
        truth, match, bev, iou3, any3 = pairs(cars(pred), gt, args.score_min)
        rng = np.hypot(truth[:, 0], truth[:, 1])
        for lo, hi in BANDS:
            band = (rng >= lo) & (rng < hi)
            hit = band & (bev >= 0.7)
            t, p = truth[hit], match[hit]
            ray = t[:, :2] / np.linalg.norm(t[:, :2], axis=1, keepdims=True)
            d = p[:, :2] - t[:, :2]
            radial = np.abs((d * ray).sum(1))
            across = np.abs(d[:, 0] * ray[:, 1] - d[:, 1] * ray[:, 0])
            dz, dl, dw, dh = (p[:, i] - t[:, i] for i in (2, 3, 4, 5))
            dyaw = np.degrees(np.abs(wrap_angle(p[:, 6] - t[:, 6])))
            dyaw = np.minimum(dyaw, 180 - dyaw)
            errors = " | ".join(median_abs(v) for v in (radial, across, dz, dl, dw, dh))
            print(
                f"| {name} | {lo}-{hi} | {band.sum()} | {(band & (any3 >= 0.7)).sum()} "
                f"| {hit.sum()} | {errors} | {np.median(dyaw):.2f} | {dz.mean():+.3f} "
                f"| {dh.mean():+.3f} |"
            )


if __name__ == "__main__":
    main()
