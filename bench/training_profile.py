"""Where a training step's time goes (not a test): cProfile of the first steps of an epoch on a
streamed frame set, 0 loader workers (the samples made in the step, so that they are counted),
1 thread; prints the cumulative seconds of the input pipeline's and the step's parts.

Usage:
  .venv/bin/python bench/training_profile.py --data DIR [--steps 8] [--batch-size 2]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

import torch

from dali_cli.detector import Augmentation, DetectorConfig, PillarCenterNet, TrainSettings, train
from dali_cli.detector.data import load_labeled
from dali_cli.detector.training_stage import attach_database

PARTS = {
    "augmented_sample", "frame", "sample_ground_truth", "object_noise", "collate",
    "build_targets", "optimize_step", "forward", "backward", "detection_loss", "add_refine_loss",
    "refine_loss", "point_box_pairs", "cell_iou_targets", "peak_iou_loss", "iou_3d", "step",
}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--batch-size", type=int, default=2)
    args = parser.parse_args()
    config = DetectorConfig()
    data = load_labeled(args.data, config, stream=True)
    config.sensor, config.mount_height_m = data.sensor, data.mount_height_m
    attach_database(data, config, augment=True)
    torch.manual_seed(0)
    net = PillarCenterNet(config)
    settings = TrainSettings(
        epochs=args.steps * args.batch_size / len(data), batch_size=args.batch_size, seed=0,
        threads=1, loader_workers=0, log_every=1000,
    )  # fmt: skip
    profile = cProfile.Profile()
    started = time.perf_counter()
    profile.enable()
    result = train(net, [data], [Augmentation()], settings, progress=False)
    profile.disable()
    print(f"{result.steps} steps in {time.perf_counter() - started:.1f} s")
    stats = pstats.Stats(profile).stats
    for (file, line, name), (_, calls, _, cumulative, _) in sorted(
        stats.items(), key=lambda item: -item[1][3]
    ):
        if name in PARTS and ("dali_cli" in file or "torch" in file):
            where = file.split("site-packages/")[-1]
            print(f"{cumulative:8.2f} s {calls:6d} calls  {name}  {where}:{line}")


if __name__ == "__main__":
    main()
