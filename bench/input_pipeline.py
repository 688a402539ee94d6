"""Input pipeline benchmark (not a test): what the training input costs the host and how much
of a training step waits for it.

1. pipeline alone: host ms per training frame (wall and CPU) of reading a frame from frames.zarr, augmenting
   it (gt sampling from the cached database, object noise, flip, rotation, scaling) and building
   its batch's targets (loader.TrainingSamples + collate), in this process, one thread: what one
   DataLoader worker spends per frame;
2. training: frames/s of `train` (the first `--steps` steps of an epoch on the streamed set) with
   each number of loader workers, and the share of the step time spent waiting for data (the
   train log's data_wait_share, averaged over the logged windows after the first).

Run it with the PYTHONPATH of another checkout and `--workers none` to measure a `train` without
the loader (its frames/s), on the same frames.

Usage:
  .venv/bin/python bench/input_pipeline.py --data DIR [--frames 24] [--steps 12]
      [--batch-size 2] [--workers 0,1,2 | none] [--threads N] [--label NAME]
      -> bench/results/input_pipeline.json (one entry per label)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from dali_cli.detector import Augmentation, DetectorConfig, PillarCenterNet, TrainSettings, train
from dali_cli.detector.data import load_labeled

try:
    from dali_cli.runtime.machine import available_cores, cpu_model
except ImportError:  # a checkout from before runtime.machine
    from dali_cli.detector.runtime import available_cores, cpu_model
from dali_cli.detector.training_stage import attach_database

RESULT = Path(__file__).parent / "results" / "input_pipeline.json"


def streamed(data_dir: str, config: DetectorConfig):
    try:
        data = load_labeled(data_dir, config, stream=True)
    except TypeError:  # a checkout without streaming: frames in memory
        data = load_labeled(data_dir, config)
    config.sensor, config.mount_height_m = data.sensor, data.mount_height_m
    attach_database(data, config, augment=True)
    return data


def pipeline_ms_per_frame(data, config, frames: int, batch_size: int) -> tuple[float, float]:
    """(wall, CPU) ms per frame of making `frames` samples and their batches, one thread."""
    from dali_cli.detector.loader import TrainingSamples, collate

    torch.set_num_threads(1)
    samples = TrainingSamples([data], [Augmentation()], seed=0)
    order = np.random.default_rng(0).permutation(len(data))[:frames]
    started, cpu = time.perf_counter(), time.process_time()
    for start in range(0, frames, batch_size):
        items = [
            samples[(0, int(i), start, j)] for j, i in enumerate(order[start : start + batch_size])
        ]
        collate(items, config)
    wall, cpu = time.perf_counter() - started, time.process_time() - cpu
    return round(1000 * wall / frames, 1), round(1000 * cpu / frames, 1)


def training_rate(
    data, config, steps: int, batch_size: int, workers: int | None, threads: int | None
) -> dict:
    torch.manual_seed(0)
    net = PillarCenterNet(config)
    extra = {} if workers is None else {"loader_workers": workers}
    settings = TrainSettings(
        epochs=steps * batch_size / len(data), batch_size=batch_size, seed=0, log_every=2,
        device="cpu", threads=threads, **extra,
    )  # fmt: skip
    result = train(net, [data], [Augmentation()], settings, progress=False)
    later = result.log[1:]  # the first window holds the start-up
    rate = float(np.mean([r["frames_per_s"] for r in later]))
    wait = [r.get("data_wait_share") for r in later]
    return {
        "workers": workers,
        "steps": result.steps,
        "frames_per_s_total": round(result.frames / result.seconds, 3),
        "frames_per_s_after_first_window": round(rate, 3),
        "data_wait_share": None if None in wait else round(float(np.mean(wait)), 3),
        "torch_threads": result.runtime.get("threads"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--steps", type=int, default=12)
    parser.add_argument("--batch-size", type=int, default=2)
    parser.add_argument("--workers", default="0,1,2")
    parser.add_argument("--label", default="streaming")
    parser.add_argument("--threads", type=int, default=None, help="the training's torch threads")
    args = parser.parse_args()
    config = DetectorConfig()
    data = streamed(args.data, config)
    entry = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "command": " ".join(sys.argv),
        "load_1m_before": os.getloadavg()[0],
        "frames_in_set": len(data),
    }
    if args.workers != "none":
        wall, cpu = pipeline_ms_per_frame(data, config, args.frames, args.batch_size)
        entry["pipeline_ms_per_frame_1_thread"] = {"wall": wall, "cpu": cpu}
        print(json.dumps(entry), flush=True)
    counts = [None] if args.workers == "none" else [int(w) for w in args.workers.split(",") if w]
    entry["training"] = []
    for workers in counts:
        entry["training"].append(
            training_rate(data, config, args.steps, args.batch_size, workers, args.threads)
        )
        print(json.dumps(entry["training"][-1]), flush=True)
    entry["load_1m_after"] = os.getloadavg()[0]
    results = json.loads(RESULT.read_text()) if RESULT.is_file() else {"runs": {}}
    results["machine"] = {"cpu": cpu_model(), "cores_available": available_cores()}
    results["runs"][args.label] = entry
    RESULT.parent.mkdir(parents=True, exist_ok=True)
    RESULT.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
