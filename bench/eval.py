"""Benchmark of dali's geometry and evaluator: IoU pairs/s and `dali eval` time at KITTI-val size.

Writes bench/results/eval.json. Run: `.venv/bin/python bench/eval.py [--quick]`.
Timings are the best of a few repeats (wall clock); the load average is recorded with them,
because the 2-core development machine is shared.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from pareto.common import best_seconds

from dali_cli import geometry
from dali_cli.evaluation.evaluate import evaluate
from dali_cli.importers.kitti_label import write_label_dir
from dali_cli.store.artifacts import BoxTable, write_boxes

RESULTS = Path(__file__).resolve().parent / "results" / "eval.json"
CAR = (3.9, 1.6, 1.5)


def random_boxes(rng, count, spread):
    return np.c_[
        rng.uniform(-spread, spread, (count, 2)),
        rng.uniform(-1, 0, count),
        rng.uniform(0.5, 5.0, (count, 3)),
        rng.uniform(-np.pi, np.pi, count),
    ]


def kitti_val_like(rng, frames: int, per_frame: int):
    """GT and predictions: `per_frame` cars per frame, 80 % found with noise, plus false ones."""
    count = frames * per_frame
    frame_id = np.repeat([f"{k:06d}" for k in range(frames)], per_frame)
    centre = np.c_[rng.uniform(3, 75, count), rng.uniform(-35, 35, count)]
    gt = np.c_[
        centre,
        rng.uniform(-1.2, -0.6, count),
        rng.normal(CAR, 0.15, (count, 3)),
        rng.uniform(-np.pi, np.pi, count),
    ]
    found = rng.uniform(size=count) < 0.8
    pred = (
        gt
        + np.c_[
            rng.normal(0, 0.2, (count, 3)),
            rng.normal(0, 0.1, (count, 3)),
            rng.normal(0, 0.05, count),
        ]
    )
    pred[~found, :2] = np.c_[
        rng.uniform(3, 75, (~found).sum()), rng.uniform(-35, 35, (~found).sum())
    ]
    score = np.where(found, rng.uniform(0.3, 1.0, count), rng.uniform(0.0, 0.7, count))
    gt_table = BoxTable.from_arrays(frame_id, gt, num_points=rng.integers(0, 500, count))
    pred_table = BoxTable.from_arrays(frame_id, pred, score=score)
    return gt_table, pred_table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="smaller sizes, one repeat")
    args = parser.parse_args()
    repeats = 1 if args.quick else 3
    rng = np.random.default_rng(0)
    results: dict = {
        "machine": {
            "cpus": os.cpu_count(),
            "load_average_1min": os.getloadavg()[0],
            "python": platform.python_version(),
            "numpy": np.__version__,
        }
    }

    # 1. row-wise BEV IoU on pairs that all overlap (the clipping core, worst case)
    pairs = 50_000 if args.quick else 200_000
    a = random_boxes(rng, pairs, 5.0)
    b = a + np.c_[rng.uniform(-2, 2, (pairs, 2)), np.zeros((pairs, 4)), rng.uniform(-1, 1, pairs)]
    seconds = best_seconds(lambda: geometry.bev_iou_pairs(a, b), repeats)
    results["bev_iou_pairs_overlapping"] = {
        "pairs": pairs,
        "seconds": seconds,
        "pairs_per_s": pairs / seconds,
    }
    seconds = best_seconds(lambda: geometry.iou_pairs_bev_3d(a, b), repeats)
    results["iou_pairs_bev_3d_overlapping"] = {
        "pairs": pairs,
        "seconds": seconds,
        "pairs_per_s": pairs / seconds,
    }

    # 2. pairwise (N, M) BEV IoU of a crowded scene: most pairs are rejected by bounding circles
    n = 1000 if args.quick else 3000
    boxes = random_boxes(rng, n, 50.0)
    other = boxes + np.c_[rng.normal(0, 0.5, (n, 2)), np.zeros((n, 5))]
    seconds = best_seconds(lambda: geometry.bev_iou(boxes, other), repeats)
    results["bev_iou_pairwise_scene"] = {
        "shape": [n, n],
        "area_m": [100, 100],
        "seconds": seconds,
        "pairs_per_s": n * n / seconds,
        "nonzero_pairs": int((geometry.bev_iou(boxes, other) > 0).sum()),
    }

    # 3. shapely on the same overlapping pairs, for scale
    try:
        from shapely.geometry import Polygon

        sample = 5000
        corners_a, corners_b = geometry.bev_corners(a[:sample]), geometry.bev_corners(b[:sample])

        def with_shapely():
            for k in range(sample):
                pa, pb = Polygon(corners_a[k]), Polygon(corners_b[k])
                inter = pa.intersection(pb).area
                _ = inter / (pa.area + pb.area - inter)

        seconds = best_seconds(with_shapely, 1)
        results["shapely_pairs_per_s"] = sample / seconds
    except ImportError:
        pass

    # 4. points in boxes and NMS at detector sizes
    points = np.c_[
        rng.uniform(-70, 70, (120_000, 2)), rng.uniform(-2, 1, 120_000), rng.uniform(0, 1, 120_000)
    ]
    cars = np.c_[
        rng.uniform(-60, 60, (30, 2)),
        np.full(30, -0.9),
        np.tile(CAR, (30, 1)),
        rng.uniform(-3, 3, 30),
    ]
    seconds = best_seconds(lambda: geometry.point_box_indices(points, cars), repeats)
    results["point_box_indices"] = {"points": 120_000, "boxes": 30, "seconds": seconds}
    candidates = np.c_[
        rng.uniform(0, 70, (1000, 2)),
        rng.uniform(-1, 0, 1000),
        rng.normal(CAR, 0.2, (1000, 3)),
        rng.uniform(-3, 3, 1000),
    ]
    scores = rng.uniform(size=1000)
    seconds = best_seconds(lambda: geometry.nms_bev(candidates, scores, 0.1), repeats)
    results["nms_bev"] = {"boxes": 1000, "seconds": seconds}

    # 5. evaluation at KITTI val size: 3,769 frames x 20 boxes (GT and predictions)
    frames = 3769
    gt_table, pred_table = kitti_val_like(rng, frames, 20)
    seconds = best_seconds(lambda: evaluate(pred_table, gt_table), repeats)
    metrics = evaluate(pred_table, gt_table)["Car"]
    results["evaluate_3769x20"] = {
        "frames": frames,
        "gt_boxes": len(gt_table),
        "pred_boxes": len(pred_table),
        "protocol": metrics["protocol"],
        "seconds": seconds,
        "ap_bev_all": metrics["bev"]["all"],
        "ap_3d_all": metrics["3d"]["all"],
    }
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for name, table in (("gt", gt_table), ("pred", pred_table)):
            (tmp / name).mkdir()
            write_boxes(tmp / name, table)
        write_label_dir(tmp / "gt_labels", gt_table, with_score=False)
        write_label_dir(tmp / "pred_labels", pred_table)
        dali = str(Path(sys.executable).with_name("dali"))
        for key, pred_dir, gt_dir in (
            ("dali_eval_cli_box_tables", "pred", "gt"),
            ("dali_eval_cli_label_2", "pred_labels", "gt_labels"),
        ):
            command = [
                dali,
                "eval",
                "--pred",
                str(tmp / pred_dir),
                "--gt",
                str(tmp / gt_dir),
                "--protocol",
                "range",
            ]
            seconds = best_seconds(
                lambda command=command: subprocess.run(command, check=True, capture_output=True),
                repeats,
            )
            results[key] = {
                "frames": frames,
                "boxes_per_frame": 20,
                "seconds": seconds,
                "command": " ".join(command[1:3]) + " ...",
            }

    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
