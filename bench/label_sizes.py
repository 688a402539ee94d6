"""Benchmark: how tight and how varied are a label set's car boxes against the truth? (a diagnosis)

Scores label sets (`dali pseudo-label` or `dali track-pseudo` outputs, or any box table) against
ground truth on the ground truth's frames only (a merged target's pseudo labels restricted to
the labelled drive's frames), as `dali eval` does (the same protocol, matching and error
breakdown), and adds what the breakdown does not print: the spread of the true positives'
lengths (5-95 % range and std) beside their matched labels'. Per set: AP_BEV and AP_3D at IoU
0.7 (moderate), the AP a perfect placement of the near misses would add (`mislocalized`:
ap_fixed - ap), and the true positives' (BEV IoU > 0.5, moderate, errors.TP_IOU) median |l|, |w|
errors.

    .venv/bin/python bench/label_sizes.py --gt RUN-data/drive_labels \
        --pred median=RUN/tracked --pred fitted=RUN/tracked_fit [--out bench/results/label_sizes.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from dali_cli.evaluation.errors import TP_IOU, TP_OVERLAP, breakdown  # noqa: E402
from dali_cli.evaluation.evaluate import evaluate, matched_ground_truth, scored_boxes  # noqa: E402
from dali_cli.store.artifacts import read_boxes  # noqa: E402

PROTOCOL, GROUP, IOU = "kitti", "moderate", 0.7


def spread(values: np.ndarray) -> dict:
    """The 5 %, 50 %, 95 % quantiles, their 5-95 % range and the std of `values (n,)` (m)."""
    if not len(values):
        return {}
    p5, p50, p95 = np.quantile(values, [0.05, 0.5, 0.95])
    return {"p5": p5, "median": p50, "p95": p95, "range_5_95": p95 - p5, "std": values.std()}


def true_positive_pairs(scored) -> tuple[np.ndarray, np.ndarray]:
    """(predicted (n, 7), matched label (n, 7)) of the headline group's true positives at BEV IoU
    > TP_IOU: the pairs errors.breakdown summarizes."""
    ignored_gt, ignored_pred = scored.flags[GROUP]
    matched = matched_ground_truth(scored, TP_OVERLAP, GROUP, TP_IOU)
    true = (matched >= 0) & (ignored_pred == 0)
    true[true] = ignored_gt[matched[true]] == 0
    return scored.pred.boxes[true], scored.gt.boxes[matched[true]]


def measure(pred_dir: Path, gt) -> dict:
    """The figures of one label set (module docstring) against the ground-truth table `gt`."""
    pred = read_boxes(pred_dir)
    pred = pred.select(np.isin(pred.frame_id.astype(str), np.unique(gt.frame_id.astype(str))))
    scored = scored_boxes(pred, gt, PROTOCOL)
    metrics = evaluate(pred, gt, IOU, protocol=PROTOCOL, scored=scored)["Car"]
    block = breakdown(pred, gt, (IOU,), protocol=PROTOCOL, scored=scored)["false_positives"]
    predicted, truth = true_positive_pairs(scored)
    result = {"boxes": len(pred), "tp": len(predicted)}
    for metric in ("bev", "3d"):
        fixes = block[f"{IOU:g}"][metric]
        result[f"ap_{metric}"] = metrics[metric][GROUP]
        result[f"mislocalized_gap_{metric}"] = fixes["ap_fixed"]["mislocalized"] - fixes["ap"]
        result[f"counts_{metric}"] = fixes["counts"][GROUP]
    for k, name in ((3, "l"), (4, "w"), (5, "h")):
        result[f"median_abs_{name}_error_m"] = float(np.median(np.abs(predicted[:, k] - truth[:, k])))  # fmt: skip
    result["tp_length"] = spread(predicted[:, 3])
    result["label_length"] = spread(truth[:, 3])
    result["tp_width"] = spread(predicted[:, 4])
    result["label_width"] = spread(truth[:, 4])
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gt", type=Path, required=True, help="ground truth: a box table dir")
    parser.add_argument("--pred", action="append", required=True, help="NAME=DIR, repeatable")
    parser.add_argument("--out", type=Path, help="write the figures as JSON")
    args = parser.parse_args()
    gt = read_boxes(args.gt)
    results = {}
    for item in args.pred:
        name, _, path = item.partition("=")
        results[name] = measure(Path(path), gt)
    as_float = lambda x: round(float(x), 4) if isinstance(x, float | np.floating) else x  # noqa: E731
    text = json.dumps(results, indent=1, default=as_float)
    results = json.loads(text, parse_float=lambda s: round(float(s), 4))
    print(json.dumps(results, indent=1))
    if args.out:
        args.out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
