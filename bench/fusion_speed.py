"""CPU and wall seconds per frame of the detector alone and with each test-time fusion (flip,
scales, both; dali_cli/detector/fusion.py), the four interleaved over the same frames so that a
shared machine's load falls on all of them alike.

Run: `PYTHONPATH=. .venv/bin/python bench/fusion_speed.py --model models/kitti-hdl64e
--data runs/objects [--frames 16] [--repeats 2]` (the scale: the model's scale.json; the ground: the model's mount height).
"""

from __future__ import annotations

import argparse
import itertools
import os
import time

import torch

from dali_cli.detector import Detector
from dali_cli.detector.fusion import TestTimeFusion
from dali_cli.runtime.machine import available_cores
from dali_cli.store.artifacts import FrameSet
from dali_cli.store.scale_file import read_scale

MODES = {
    "none": None,
    "flip": TestTimeFusion(flip=True),
    "scales": TestTimeFusion(scale_factors=(0.95, 1.0, 1.05)),
    "both": TestTimeFusion(flip=True, scale_factors=(0.95, 1.0, 1.05)),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--batch-size", type=int, default=4)
    args = parser.parse_args()
    torch.set_num_threads(available_cores())
    detector, scale = Detector.load(args.model), read_scale(args.model).scale
    frames = [
        points for _, points in itertools.islice(FrameSet(args.data).iter_frames(), args.frames)
    ]
    cpu, wall = dict.fromkeys(MODES, 0.0), dict.fromkeys(MODES, 0.0)
    for _ in range(args.repeats):
        for name, fusion in MODES.items():
            started_cpu, started = time.process_time(), time.perf_counter()
            for start in range(0, len(frames), args.batch_size):  # batches, as eval runs them
                chunk = frames[start : start + args.batch_size]
                if fusion is None:
                    detector.predict(chunk, scale, None, args.batch_size)
                else:
                    fusion.predict(detector, chunk, scale, None, args.batch_size)
            cpu[name] += time.process_time() - started_cpu
            wall[name] += time.perf_counter() - started
    count = args.repeats * len(frames)
    print(f"{len(frames)} frames x {args.repeats}, load average {os.getloadavg()[0]:.1f}")
    for name in MODES:
        print(
            f"{name:7s} cpu {cpu[name] / count:.3f} s/frame  wall {wall[name] / count:.3f} s/frame"
        )


if __name__ == "__main__":
    main()
