"""Training-step and inference time of the detector in fp32 and bf16 autocast.

    .venv/bin/python docs/results/exp600/bf16_speed.py RUN [--threads 1]

RUN: a finished benchmark run (runs/experiment-s0): its source frames for training steps (the
first 32, all augmentations, batch 1, 4 warm-up steps, then the median of 10) and its x2 model on
24 target frames at s = 1.18 for inference (after a 4-frame warm-up), with the number of boxes at
score >= 0.3 and their mean size, to see that bf16 finds the same boxes."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from dali_cli.detector import (
    Augmentation,
    Detector,
    DetectorConfig,
    PillarCenterNet,
    TrainSettings,
    load_labeled,
)
from dali_cli.detector.augment import ObjectDatabase
from dali_cli.detector.data import detection_region
from dali_cli.detector.train import interleave, optimize_step, step_samples
from dali_cli.runtime.machine import cpu_model
from dali_cli.store.artifacts import FrameSet


def training_frames(run: Path, config: DetectorConfig):
    """The run's first 32 source frames with their labels and object database."""
    data = load_labeled(str(run / "data" / "source"), config)
    data.points, data.boxes, data.frame_ids = data.points[:32], data.boxes[:32], data.frame_ids[:32]
    data.database = ObjectDatabase.build(data.points, data.boxes, region=detection_region(config))
    return data


def step_ms(data, config: DetectorConfig, precision: str, threads: int) -> float:
    torch.manual_seed(0)
    net = PillarCenterNet(config)
    net.train()
    settings = TrainSettings(epochs=1, batch_size=1, threads=threads, precision=precision)
    optimizer = torch.optim.AdamW(net.parameters(), lr=1e-3)
    pattern = interleave(settings.mix)
    took = []
    for step in range(14):
        started = time.perf_counter()
        _, samples = step_samples([data], [Augmentation()], pattern, step, 1, settings, [0])
        optimize_step(net, net, optimizer, samples, settings, torch.device("cpu"), step, [0])
        took.append(time.perf_counter() - started)
    return float(np.median(took[4:]) * 1000)


def inference(run: Path, points: list, precision: str) -> tuple[float, int, np.ndarray]:
    detector = Detector.load(run / "iter2" / "model", precision=precision)
    detector.predict(points[:4], scale=1.18)
    started = time.perf_counter()
    out = detector.predict(points, scale=1.18)
    seconds = (time.perf_counter() - started) / len(points)
    kept = [boxes[scores >= 0.3] for boxes, scores in out]
    return seconds, sum(len(k) for k in kept), np.concatenate(kept)[:, 3:6].mean(axis=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("run", type=Path)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"{cpu_model()}, {args.threads} thread(s)")
    config = DetectorConfig()
    data = training_frames(args.run, config)
    frames = FrameSet(args.run / "data" / "target")
    points = [frames.frame(i) for i in range(24)]
    for precision in ("fp32", "bf16", "fp32", "bf16"):  # alternating: drifts in load show
        ms = step_ms(data, config, precision, args.threads)
        seconds, boxes, size = inference(args.run, points, precision)
        print(
            f"{precision}: training {ms:.0f} ms/step, inference {seconds:.3f} s/frame, "
            f"{boxes} boxes at score >= 0.3, mean l/w/h {np.round(size, 3).tolist()}"
        )


if __name__ == "__main__":
    main()
