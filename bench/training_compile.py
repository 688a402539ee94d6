"""torch.compile against eager for the part of a training step where its time goes (not a test):
forward and backward of the backbone and heads of a model's configuration on a fixed batch of
random canvases, one thread, the two interleaved; prints the compile time and each one's median
step.

Usage:
  .venv/bin/python bench/training_compile.py --model models/kitti-hdl64e [--steps 6]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from dali_cli.detector import Detector
from dali_cli.detector.model import Backbone, CenterHead


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--model", required=True, help="a model directory, e.g. models/kitti-hdl64e"
    )
    parser.add_argument("--steps", type=int, default=6)
    parser.add_argument("--batch-size", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(1)
    config = Detector.load(args.model).config
    torch.manual_seed(0)
    net = torch.nn.Sequential(Backbone(config), CenterHead(config))
    canvas = torch.randn(args.batch_size, config.pfn_channels, *config.grid_size)  # (B, C, H, W)

    def step(module: torch.nn.Module) -> float:
        started = time.perf_counter()
        maps = module(canvas)
        sum(value.float().square().mean() for value in maps.values()).backward()
        return time.perf_counter() - started

    started = time.perf_counter()
    compiled = torch.compile(net)
    step(compiled), step(compiled)
    print(
        f"canvas {tuple(canvas.shape)}; compile and 2 steps: {time.perf_counter() - started:.0f} s"
    )
    times = {"eager": [], "compiled": []}
    for _ in range(args.steps):
        times["eager"].append(step(net))
        times["compiled"].append(step(compiled))
    for name, values in times.items():
        spread = ", ".join(f"{v:.2f}" for v in values)
        print(f"{name}: median step {statistics.median(values):.3f} s ({spread})")


if __name__ == "__main__":
    main()
