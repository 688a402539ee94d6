"""Diagnostic box set (reads target labels: never a DALI stage): the cars the pseudo labels found,
each with its true pose (centre x, y, heading, and bottom height) but the pseudo box's size
(l, w, h). Between the session-12 `truth-matched` set (true boxes of the same cars) and the
pseudo boxes themselves: does the gain of the true boxes come from where they are or from their
size? Pairs as docs/results/demo6/hybrid_boxes.py (greedy by score, BEV IoU > 0.3).

    python docs/results/demo7/pose_size.py --truth RUN/data/target --pseudo DIR --out DIR
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

from dali_cli.artifacts import BoxTable, read_boxes, write_boxes  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--truth", type=Path, required=True)
    parser.add_argument("--pseudo", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    truth = read_boxes(args.truth)
    truth = truth.select(np.flatnonzero(np.asarray(truth["label"]).astype(str) == "Car"))
    pseudo = read_boxes(args.pseudo)
    truth_rows = truth.rows_by_frame()
    ids, boxes, scores = [], [], []
    for frame_id, rows in pseudo.rows_by_frame().items():
        t_rows = truth_rows.get(frame_id, np.zeros(0, np.int64))
        matched = match(pseudo.boxes[rows], pseudo["score"][rows], truth.boxes[t_rows], 0.3)
        hit = matched >= 0
        true, found = truth.boxes[t_rows[matched[hit]]], pseudo.boxes[rows[hit]]
        box = true.copy()
        box[:, 3:6] = found[:, 3:6]  # the pseudo size
        box[:, 2] = true[:, 2] - true[:, 5] / 2 + found[:, 5] / 2  # on the true bottom
        ids += [frame_id] * len(box)
        boxes.append(box)
        scores.append(pseudo["score"][rows[hit]])
    out = BoxTable.from_arrays(np.asarray(ids), np.concatenate(boxes), score=np.concatenate(scores))
    args.out.mkdir(parents=True, exist_ok=True)
    write_boxes(args.out, out)
    record = {"command": " ".join(sys.argv), "boxes": len(out), "pseudo_boxes": len(pseudo)}
    (args.out / "pose_size.json").write_text(json.dumps(record, indent=2) + "\n")
    print(json.dumps(record))


if __name__ == "__main__":
    main()
