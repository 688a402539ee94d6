"""Benchmark: how good are a run's pseudo labels? (a diagnosis)

Reads pseudo-label directories (`dali pseudo-label` outputs) and the target's *held-back* labels
(a bench may read them; no DALI stage does) and measures, per range band of the detection grid:
precision and recall of the pseudo boxes (greedy matching by score, BEV IoU > --iou), the mean
l, w, h of the pseudo boxes vs the true mean of the target's cars, and the size error of matched
pairs (pseudo - truth), so the per-dimension size correction can be judged on real labels; and
what the false positives are: "hallucinated" (centre >= 2 m from every labeled car of the frame,
in the grid or not: clutter taken for a car) or "near a car" (a duplicate or a loose box), their
median score and points against the true positives', how many are dense (>= 300 points, which
RC leaves as they are), and the true / false positives kept at higher score cuts (what `pseudo-label --score-min` would keep).

    .venv/bin/python bench/pseudo_labels.py --target RUN/data/target \
        --pseudo RUN/iter1/pseudo_raw RUN/iter1/pseudo [--iou 0.5] [--out bench/results/pseudo_labels.json]

Only the pseudo boxes on the labelled set's frames count (a target of several drives is
pseudo-labelled on every drive; the labels may cover one).

Truth counted: every target label of class Car inside the detection grid (x 0..70.4 m,
|y| <= 40 m, the detector's default range) with at least --min-points points.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from dali_cli.geometry import bev_iou  # noqa: E402
from dali_cli.runtime.machine import cpu_model  # noqa: E402
from dali_cli.store.artifacts import FrameSet, read_boxes  # noqa: E402

BANDS = ((0.0, 30.0), (30.0, 50.0), (50.0, 80.0))
GRID_X, GRID_Y = (0.0, 70.4), 40.0
HALLUCINATED_M = 2.0  # a false positive this far from every labeled car is clutter, not a loose box
SCORE_CUTS = (0.3, 0.4, 0.5, 0.6)
DENSE_POINTS = 300  # ppcg-rc leaves boxes with this many points or more as they are (RcParams)


def in_grid(boxes: np.ndarray) -> np.ndarray:
    """(N,) bool: box centre inside the detector's default BEV range."""
    return (boxes[:, 0] >= GRID_X[0]) & (boxes[:, 0] < GRID_X[1]) & (np.abs(boxes[:, 1]) <= GRID_Y)


def match(pred: np.ndarray, scores: np.ndarray, truth: np.ndarray, iou: float) -> np.ndarray:
    """Greedy by descending score: index of the matched truth box per prediction, -1 if none."""
    matched = np.full(len(pred), -1, np.int64)
    if not len(pred) or not len(truth):
        return matched
    overlaps = bev_iou(pred, truth)  # (P, T)
    taken = np.zeros(len(truth), bool)
    for p in np.argsort(-scores, kind="stable"):
        candidates = np.where(taken, -1.0, overlaps[p])
        best = int(np.argmax(candidates))
        if candidates[best] > iou:
            matched[p], taken[best] = best, True
    return matched


def evaluate(
    pseudo_dir: Path, truth_table, iou: float, min_points: int, frames: set | None = None
) -> dict:
    """Pseudo boxes against `truth_table`; with `frames` (the labelled set's frame ids) only
    those on its frames."""
    pseudo = read_boxes(pseudo_dir)
    if frames is not None:
        pseudo = pseudo.select(np.isin(pseudo.frame_id.astype(str), sorted(frames)))
    truth_rows, pseudo_rows = truth_table.rows_by_frame(), pseudo.rows_by_frame()
    pred_range, truth_range, pred_hit, truth_hit, size_error = [], [], [], [], []
    car_distance, scores, points = [], [], []
    for frame_id in sorted(set(truth_rows) | set(pseudo_rows)):
        every_car = truth_table.boxes[truth_rows.get(frame_id, np.zeros(0, np.int64))]
        t_points = truth_table["num_points"][truth_rows.get(frame_id, np.zeros(0, np.int64))]
        t = every_car[in_grid(every_car) & (t_points >= min_points)]
        rows = pseudo_rows.get(frame_id, np.zeros(0, np.int64))
        p, s, n = pseudo.boxes[rows], pseudo["score"][rows], pseudo["num_points"][rows]
        keep = in_grid(p)
        p, s, n = p[keep], s[keep], n[keep]
        gaps = np.linalg.norm(p[:, None, :2] - every_car[None, :, :2], axis=2)  # (P, every car)
        car_distance.append(gaps.min(axis=1) if every_car.size else np.full(len(p), np.inf))
        scores.append(s)
        points.append(n)
        matched = match(p, s, t, iou)
        hit = np.zeros(len(t), bool)
        hit[matched[matched >= 0]] = True
        pred_range.append(np.hypot(p[:, 0], p[:, 1]))
        truth_range.append(np.hypot(t[:, 0], t[:, 1]))
        pred_hit.append(matched >= 0)
        truth_hit.append(hit)
        size_error.append(p[matched >= 0, 3:6] - t[matched[matched >= 0], 3:6])
    pred_range, truth_range = np.concatenate(pred_range), np.concatenate(truth_range)
    pred_hit, truth_hit = np.concatenate(pred_hit), np.concatenate(truth_hit)
    size_error = np.concatenate(size_error)
    car_distance, scores = np.concatenate(car_distance), np.concatenate(scores)
    points = np.concatenate(points)
    bands = {}
    for lo, hi in (*BANDS, (0.0, np.inf)):
        name = "all" if hi == np.inf else f"{lo:.0f}-{hi:.0f}"
        in_p = (pred_range >= lo) & (pred_range < hi)
        in_t = (truth_range >= lo) & (truth_range < hi)
        bands[name] = {
            "pseudo_boxes": int(in_p.sum()),
            "true_cars": int(in_t.sum()),
            "true_positives": int(pred_hit[in_p].sum()),
            "false_positives": int((~pred_hit[in_p]).sum()),
            "missed_cars": int((~truth_hit[in_t]).sum()),
            "precision": round(float(pred_hit[in_p].mean()), 4) if in_p.any() else None,
            "recall": round(float(truth_hit[in_t].mean()), 4) if in_t.any() else None,
        }
    summary = json.loads((pseudo_dir / "summary.json").read_text())
    return {
        "pseudo": str(pseudo_dir),
        "boxes": len(pseudo),
        "mean_lwh_pooled": [round(float(v), 4) for v in pseudo.boxes[:, 3:6].mean(axis=0)],
        "mean_lwh_per_frame": summary.get("mean_lwh"),
        "size_correction": summary.get("size_correction"),
        "matched_size_error_lwh": [round(float(v), 4) for v in size_error.mean(axis=0)],
        "matched_pairs": len(size_error),
        "bands": bands,
        **false_positive_kinds(pred_hit, car_distance, scores, points),
    }


def false_positive_kinds(hit, car_distance, scores, points) -> dict:
    """The true positives and the two kinds of false positive (count, median score and points,
    dense boxes), and how many of each kind higher score cuts keep. hit, car_distance (m),
    scores, points: (P,) per pseudo box in the grid."""
    kinds = {
        "true_positives": hit,
        "near_a_car": ~hit & (car_distance < HALLUCINATED_M),
        "hallucinated": ~hit & (car_distance >= HALLUCINATED_M),
    }
    summary = {
        name: {
            "boxes": int(chosen.sum()),
            "median_score": round(float(np.median(scores[chosen])), 3) if chosen.any() else None,
            "median_points": float(np.median(points[chosen])) if chosen.any() else None,
            "dense": int((chosen & (points >= DENSE_POINTS)).sum()),
        }
        for name, chosen in kinds.items()
    }
    cuts = {}
    for cut in SCORE_CUTS:
        kept = scores >= cut
        cuts[f"{cut:.1f}"] = {
            "true_positives": int((kinds["true_positives"] & kept).sum()),
            "false_positives": int((~hit & kept).sum()),
            "hallucinated": int((kinds["hallucinated"] & kept).sum()),
        }
    return {"false_positives": summary, "score_cuts": cuts}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--target", type=Path, required=True, help="target FrameSet with labels")
    parser.add_argument("--pseudo", type=Path, nargs="+", required=True)
    parser.add_argument("--iou", type=float, default=0.5, help="BEV IoU for a match (>)")
    parser.add_argument("--min-points", type=int, default=1)
    parser.add_argument("--out", type=Path, default=ROOT / "bench/results/pseudo_labels.json")
    args = parser.parse_args()
    truth = read_boxes(args.target)
    truth = truth.select(np.asarray(truth["label"]).astype(str) == "Car")
    frames = set(FrameSet(args.target).frame_ids)
    grid = in_grid(truth.boxes) & (truth["num_points"] >= args.min_points)
    result = {
        "command": "bench/pseudo_labels.py " + " ".join(sys.argv[1:]),
        "machine": {"cpu_model": cpu_model(), "load_1min": round(os.getloadavg()[0], 2)},
        "python": platform.python_version(),
        "iou_bev": args.iou,
        "truth": {
            "cars_in_grid": int(grid.sum()),
            "mean_lwh_in_grid": [round(float(v), 4) for v in truth.boxes[grid, 3:6].mean(axis=0)],
            "mean_lwh_all": [round(float(v), 4) for v in truth.boxes[:, 3:6].mean(axis=0)],
        },
        "pseudo": [evaluate(p, truth, args.iou, args.min_points, frames) for p in args.pseudo],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
