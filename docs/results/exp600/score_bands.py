"""Diagnostic (reads the target's labels: never a DALI stage): what do the pseudo-labeller's
low-score boxes hold? Pairs each frame's boxes (all scores, as `dali pseudo-label --score-min
0.05` writes them) with its true cars one to one (greedy by score, BEV IoU > 0.3;
bench/pseudo_labels.match) and prints, per score band, how many boxes it has and the share that
are true cars; then, of the true cars in the detection region (front, x 0-70.4 m, |y| < 40 m,
>= 5 target points) that no box at or above --score-min (the pseudo labels' cut) found, the share
a box of each lower band found: the missed cars an ignore region over that band would stop
teaching as background, per range band of the true car.

    python docs/results/exp600/score_bands.py --truth RUN/data/target --boxes DIR [--score-min 0.3]
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

from dali_cli.store.artifacts import read_boxes  # noqa: E402

SCORE_BANDS = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5, 0.6, 0.7, 0.8, 1.01)
RANGE_BANDS = ((0.0, 30.0), (30.0, 50.0), (50.0, 80.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--truth", type=Path, required=True)
    parser.add_argument("--boxes", type=Path, required=True)
    parser.add_argument("--score-min", type=float, default=0.3)
    args = parser.parse_args()
    truth = read_boxes(args.truth)
    truth = truth.select(np.flatnonzero(np.asarray(truth["label"]).astype(str) == "Car"))
    boxes = read_boxes(args.boxes)
    truth_rows = truth.rows_by_frame()
    score_all, true_all = [], []  # per box: score, is a true car
    found_by = np.full(len(truth), np.nan)  # per true car: score of the box that found it
    for frame_id, rows in boxes.rows_by_frame().items():
        t_rows = truth_rows.get(frame_id, np.zeros(0, np.int64))
        scores = np.asarray(boxes["score"])[rows]
        matched = match(boxes.boxes[rows], scores, truth.boxes[t_rows], 0.3)  # (K,) true index
        score_all.append(scores)
        true_all.append(matched >= 0)
        found_by[t_rows[matched[matched >= 0]]] = scores[matched >= 0]
    score_all, true_all = np.concatenate(score_all), np.concatenate(true_all)
    print("| score band | boxes | true cars among them |")
    print("|---|---|---|")
    for lo, hi in zip(SCORE_BANDS[:-1], SCORE_BANDS[1:], strict=True):
        band = (score_all >= lo) & (score_all < hi)
        share = f"{true_all[band].mean():.3f}" if band.any() else "-"  # no box in the band
        print(f"| {lo:.2f}-{min(hi, 1.0):.2f} | {band.sum()} | {share} |")
    t = truth.boxes
    region = (t[:, 0] >= 0) & (t[:, 0] < 70.4) & (np.abs(t[:, 1]) < 40)
    region &= np.asarray(truth["num_points"]) >= 5
    distance = np.hypot(t[:, 0], t[:, 1])
    missed = region & ~(found_by >= args.score_min)
    print()
    print("| range m | true cars | missed at the cut | of those found by a box scored 0.05-0.1 / 0.1-0.2 / 0.2-cut |")
    print("|---|---|---|---|")
    for lo, hi in RANGE_BANDS:
        here = (distance >= lo) & (distance < hi)
        m = missed & here
        shares = [
            float(((found_by >= a) & (found_by < b))[m].mean()) if m.any() else float("nan")
            for a, b in ((0.05, 0.1), (0.1, 0.2), (0.2, args.score_min))
        ]
        print(
            f"| {lo:.0f}-{hi:.0f} | {(region & here).sum()} | {m.sum()} | "
            + " / ".join(f"{s:.3f}" for s in shares)
            + " |"
        )


if __name__ == "__main__":
    main()
