"""Diagnostic box sets between the pseudo labels and the truth (reads target labels: never a DALI
stage). Pairs each frame's pseudo boxes with its true cars one to one (greedy by score, BEV IoU >
--iou) and writes OUT/boxes.parquet:

  pseudo-matched: the matched pseudo boxes (the false ones dropped; the pseudo placement kept)
  truth-matched:  the true boxes of the same cars (placement and size exact; the same cars missed)
  truth-pose:     the same cars at their true pose (centre, heading, bottom) with the pseudo
                  box's size
  truth-all:      every true car with at least --min-points points in the detector's grid (x 0 to
                  70.4, |y| <= 40 m: DetectorConfig), found or missed, score 1 (the labels a
                  perfect detector would give: the ceiling of PPCG's retraining)

    python docs/results/exp600/hybrid_boxes.py --truth RUN/data/target --pseudo RUN/iter1/pseudo \
        --mode truth-matched --out DIR
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from pseudo_labels import match  # noqa: E402

from dali_cli.store.artifacts import BoxTable, read_boxes, write_boxes  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--truth", type=Path, required=True)
    parser.add_argument("--pseudo", type=Path, required=True)
    parser.add_argument(
        "--mode", choices=["pseudo-matched", "truth-matched", "truth-pose", "truth-all"],
        required=True,
    )  # fmt: skip
    parser.add_argument("--iou", type=float, default=0.3)
    parser.add_argument("--min-points", type=int, default=1, help="truth-all: points per car")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    truth = read_boxes(args.truth)
    truth = truth.select(np.flatnonzero(np.asarray(truth["label"]).astype(str) == "Car"))
    pseudo = read_boxes(args.pseudo)
    if args.mode == "truth-all":
        from dali_cli.detector.config import DetectorConfig

        grid = DetectorConfig()
        x, y = truth.boxes[:, 0], truth.boxes[:, 1]
        keep = (truth["num_points"] >= args.min_points) & (x >= grid.x_range_m[0])
        keep &= (x <= grid.x_range_m[1]) & (y >= grid.y_range_m[0]) & (y <= grid.y_range_m[1])
        out = truth.select(np.flatnonzero(keep))
        out = BoxTable.from_arrays(out.frame_id, out.boxes, num_points=out["num_points"])
        return write(args, out, pseudo)
    truth_rows, pseudo_rows = truth.rows_by_frame(), pseudo.rows_by_frame()
    ids, boxes, scores, counts = [], [], [], []
    for frame_id, rows in pseudo_rows.items():
        t_rows = truth_rows.get(frame_id, np.zeros(0, np.int64))
        matched = match(pseudo.boxes[rows], pseudo["score"][rows], truth.boxes[t_rows], args.iou)
        hit = matched >= 0
        if args.mode == "pseudo-matched":
            chosen, table = rows[hit], pseudo
        else:
            chosen, table = t_rows[matched[hit]], truth
        ids += [frame_id] * len(chosen)
        box = table.boxes[chosen]
        if args.mode == "truth-pose":
            found = pseudo.boxes[rows[hit]]
            box[:, 2] += (found[:, 5] - box[:, 5]) / 2  # on the true bottom
            box[:, 3:6] = found[:, 3:6]  # the pseudo size
        boxes.append(box)
        scores.append(pseudo["score"][rows[hit]])
        counts.append(table["num_points"][chosen])
    out = BoxTable.from_arrays(
        np.asarray(ids), np.concatenate(boxes), score=np.concatenate(scores),
        num_points=np.concatenate(counts),
    )  # fmt: skip
    write(args, out, pseudo)


def write(args, out: BoxTable, pseudo: BoxTable) -> None:
    """OUT/boxes.parquet and OUT/hybrid.json (the command, how many boxes)."""
    args.out.mkdir(parents=True, exist_ok=True)
    write_boxes(args.out, out)
    record = {"command": " ".join(sys.argv), "boxes": len(out), "pseudo_boxes": len(pseudo)}
    (args.out / "hybrid.json").write_text(json.dumps(record, indent=2) + "\n")
    print(json.dumps(record))


if __name__ == "__main__":
    main()
