"""Diagnostic (reads the target's labels: never a DALI stage): how well do pseudo boxes fit the
cars they found? Pairs each frame's boxes with its true cars one to one (greedy by score, BEV IoU
> 0.3; bench/pseudo_labels.match) and prints, per box table: matched boxes, mean |error| along
and across the true car (m), mean yaw error up to a half turn (deg), the share with 3D IoU >= 0.7,
the mean 3D IoU, and the share whose heading is right (cos of the yaw difference > 0; PPCG places
its car model that way round).

    python docs/results/exp600/label_quality.py --truth RUN/data/target --boxes DIR [DIR ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from pseudo_labels import match  # noqa: E402

from dali_cli.geometry import iou_3d_pairs, wrap_angle  # noqa: E402
from dali_cli.store.artifacts import read_boxes  # noqa: E402


def matched_pairs(truth, boxes) -> tuple[np.ndarray, np.ndarray]:
    """The boxes of `boxes` paired one to one with true cars of `truth` in the same frame (greedy
    by score, BEV IoU > 0.3): pseudo (P, 7) and true (P, 7) float64 boxes, row p a pair."""
    truth_rows = truth.rows_by_frame()
    pred, true = [], []
    for frame_id, rows in boxes.rows_by_frame().items():
        t_rows = truth_rows.get(frame_id, np.zeros(0, np.int64))
        matched = match(boxes.boxes[rows], boxes["score"][rows], truth.boxes[t_rows], 0.3)
        pred.append(boxes.boxes[rows[matched >= 0]])
        true.append(truth.boxes[t_rows[matched[matched >= 0]]])
    return np.concatenate(pred), np.concatenate(true)


def quality(truth, boxes) -> dict:
    """The measures of the module docstring for one box table against the truth table."""
    pred, true = matched_pairs(truth, boxes)
    c, s = np.cos(true[:, 6]), np.sin(true[:, 6])
    d = pred[:, :2] - true[:, :2]
    along, across = np.abs(c * d[:, 0] + s * d[:, 1]), np.abs(-s * d[:, 0] + c * d[:, 1])
    turn = wrap_angle(pred[:, 6] - true[:, 6])
    half_turn = np.degrees(np.abs(wrap_angle(2 * turn) / 2))
    iou = iou_3d_pairs(pred, true)
    return {
        "matched": len(pred),
        "along_m": float(along.mean()),
        "across_m": float(across.mean()),
        "yaw_deg": float(half_turn.mean()),
        "iou3d_ge_0.7": float((iou >= 0.7).mean()),
        "mean_iou3d": float(iou.mean()),
        "heading_right": float((np.cos(turn) > 0).mean()),
    }


def truth_and_box_dirs(doc: str):
    """Parse --truth DIR --boxes DIR [DIR ...] (the script's help from `doc`): the truth table's
    cars and the box directories."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--truth", type=Path, required=True)
    parser.add_argument("--boxes", type=Path, nargs="+", required=True)
    args = parser.parse_args()
    truth = read_boxes(args.truth)
    return truth.select(np.flatnonzero(np.asarray(truth["label"]).astype(str) == "Car")), args.boxes


def main() -> None:
    truth, box_dirs = truth_and_box_dirs(__doc__)
    print(
        "| boxes | matched | along m | across m | yaw deg | 3D IoU >= 0.7 | mean 3D IoU | heading right |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for path in box_dirs:
        q = quality(truth, read_boxes(path))
        print(
            f"| {path} | {q['matched']} | {q['along_m']:.3f} | {q['across_m']:.3f} | "
            f"{q['yaw_deg']:.2f} | {q['iou3d_ge_0.7']:.3f} | {q['mean_iou3d']:.3f} | "
            f"{q['heading_right']:.3f} |"
        )


if __name__ == "__main__":
    main()
