"""The refiner's point crop, numpy (coarse grid, the CPU path) vs torch (brute force, the GPU
path), on training frames (not a test): CPU time per frame and the point-box pairs the torch
crop tests, checking that both pick the same points.

The proposals are those of a training step: `refine_train_peaks` boxes (here jittered copies
of the frame's labels) and the jittered labels themselves.

Usage:
  .venv/bin/python bench/refine_crop.py --data FRAMESET_DIR [--frames 10] [--device cpu]
      -> bench/results/refine_crop.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from dali_cli.detector import DetectorConfig
from dali_cli.detector.data import load_labeled
from dali_cli.detector.refine import box_point_features, box_point_features_torch, jitter_boxes
from dali_cli.runtime.machine import cpu_model

RESULT = Path(__file__).parent / "results" / "refine_crop.json"


def clock(device: torch.device, fn, *args):
    """(fn(*args), seconds): CPU time on the CPU, wall time after a synchronize on a GPU."""
    if device.type == "cuda":
        torch.cuda.synchronize()
        start = time.perf_counter()
        result = fn(*args)
        torch.cuda.synchronize()
        return result, time.perf_counter() - start
    start = time.process_time()
    result = fn(*args)
    return result, time.process_time() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(1)
    device = torch.device(args.device)
    config = DetectorConfig()
    labeled = load_labeled(args.data, config, stream=True)
    rng = np.random.default_rng(0)
    rows = []
    for index in np.linspace(0, len(labeled.points) - 1, args.frames).astype(int).tolist():
        points, labels = np.array(labeled.points[index]), labeled.boxes[index]
        if len(labels) == 0:
            continue
        copies = np.repeat(labels, -(-config.refine_train_peaks // len(labels)), axis=0)
        peaks = jitter_boxes(copies[: config.refine_train_peaks], rng)
        boxes = np.concatenate([peaks, jitter_boxes(labels, rng)])
        crop = (config.refine_points, config.refine_margin_m)
        cpu = torch.device("cpu")
        (reference, found), numpy_s = clock(cpu, box_point_features, points, boxes, *crop)
        on = torch.from_numpy(points).to(device), torch.from_numpy(boxes).to(device)
        box_point_features_torch(*on, *crop)  # warm-up
        (features, found_t), torch_s = clock(device, box_point_features_torch, *on, *crop)
        assert np.array_equal(found, found_t.cpu().numpy())
        assert np.abs(features.cpu().numpy() - reference).max() < 1e-5
        rows.append((len(points), len(boxes), numpy_s * 1e3, torch_s * 1e3))
    table = np.array(rows)
    result = {
        "data": str(args.data),
        "device": str(device),
        "cpu": cpu_model(),
        "load_1min": round(float(Path("/proc/loadavg").read_text().split()[0]), 2),
        "frames": len(rows),
        "points_mean": round(float(table[:, 0].mean())),
        "boxes_mean": round(float(table[:, 1].mean()), 1),
        "pairs_mean": round(float((table[:, 0] * table[:, 1]).mean())),
        "numpy_crop_ms_median": round(float(np.median(table[:, 2])), 2),
        "torch_crop_ms_median": round(float(np.median(table[:, 3])), 2),
        "same_points": True,
    }
    print(json.dumps(result, indent=1))
    results = json.loads(RESULT.read_text()) if RESULT.is_file() else {"runs": {}}
    results["runs"][f"{Path(args.data).name}-{device.type}"] = result
    RESULT.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
