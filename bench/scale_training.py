"""Data-parallel training benchmark (not a test): training frames/s of `dali pretrain` as one
process and as 2 torchrun (DDP, gloo) processes on this machine's CPU, through the real CLI.

Runs, each with the same global batch (2 frames per optimizer step) and the same frames:
  serial-all-cores  1 process, --threads = every available core, --batch-size 2
  serial-1-thread   1 process, --threads 1, --batch-size 2
  ddp-2             torchrun --nproc-per-node 2, default threads (cores // 2 each), --batch-size 1

frames/s is the training loop's (model.json "train", load time excluded); wall_s is the whole
command (interpreter and torch start-up of every process, data loading, training, writing).
The configurations run in `--repeats` interleaved rounds (the order rotating, as the load of a
shared machine drifts); the result keeps every run and the median frames/s of each.

Usage:
  .venv/bin/python bench/scale_training.py [--data DIR] [--frames 16] [--epochs 2] [--repeats 3]
      -> bench/results/scale_training.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from dali_cli.runtime.machine import available_cores, cpu_model

BIN = Path(sys.executable).parent
DALI = str(BIN / "dali")
RESULT = Path(__file__).parent / "results" / "scale_training.json"


def run(command: list[str], env: dict) -> float:
    """Run `command`, return its wall seconds; its stderr on failure."""
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, env=env)
    if done.returncode != 0:
        sys.exit(f"failed: {' '.join(command)}\n{done.stderr[-4000:]}")
    return time.perf_counter() - started


def pretrain_args(data: Path, out: Path, epochs: float, batch: int, extra: list[str]) -> list[str]:
    return [
        "pretrain", "--source", str(data), "--out", str(out), "--epochs", str(epochs),
        "--batch-size", str(batch), "--device", "cpu", "--quiet", "--force", *extra,
    ]  # fmt: skip


def measure(name: str, prefix: list[str], data: Path, work: Path, epochs: float, batch: int,
            extra: list[str]) -> dict:  # fmt: skip
    out = work / name
    env = dict(os.environ)
    env.pop("WORLD_SIZE", None)
    load_before = os.getloadavg()[0]
    wall = run([*prefix, *pretrain_args(data, out, epochs, batch, extra)], env)
    meta = json.loads((out / "model.json").read_text())
    manifest = json.loads((out / "manifest.json").read_text())
    summary = meta["train"]
    return {
        "processes": manifest["runtime"]["world_size"],
        "threads_per_process": manifest["runtime"]["threads"],
        "backend": manifest["runtime"].get("backend"),
        "batch_per_process": batch,
        "steps": summary["steps"],
        "frames": summary["frames"],
        "train_seconds": summary["seconds"],
        "train_frames_per_s": summary["frames_per_s"],
        "wall_s": round(wall, 1),
        "load_average_1m_before": round(load_before, 2),
        "load_average_1m_after": round(os.getloadavg()[0], 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--data", type=Path, default=None, help="labeled frame set (default: synth)"
    )
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--epochs", type=float, default=2.0)
    parser.add_argument("--repeats", type=int, default=3, help="interleaved rounds")
    parser.add_argument("--out", type=Path, default=RESULT)
    args = parser.parse_args()
    cores = available_cores()
    with tempfile.TemporaryDirectory(prefix="scale-training-") as tmp:
        work = Path(tmp)
        data = args.data
        if data is None:
            data = work / "source"
            run([DALI, "synth", "--sensor", "kitti", "--cars", "kitti", "--frames",
                 str(args.frames), "--seed", "0", "--out", str(data)], dict(os.environ))  # fmt: skip
        torchrun = [str(BIN / "torchrun"), "--standalone", "--nproc-per-node", "2", DALI]
        configs = {
            "serial-all-cores": ([DALI], 2, ["--threads", str(cores)]),
            "serial-1-thread": ([DALI], 2, ["--threads", "1"]),
            "ddp-2": (torchrun, 1, []),
        }
        runs = {name: [] for name in configs}
        for round_ in range(args.repeats):  # interleaved, the order rotating: load drifts
            names = list(configs)
            names = names[round_ % len(names) :] + names[: round_ % len(names)]
            for name in names:
                prefix, batch, extra = configs[name]
                row = measure(name, prefix, data, work, args.epochs, batch, extra)
                runs[name].append({"round": round_, **row})
                print(name, row, flush=True)
    medians = {
        name: float(np.median([row["train_frames_per_s"] for row in rows]))
        for name, rows in runs.items()
    }
    document = {
        "what": "dali pretrain training frames/s: 1 process vs 2 torchrun DDP processes (gloo, CPU)",
        "command": "python bench/scale_training.py " + " ".join(sys.argv[1:]),
        "machine": {
            "cpu_model": cpu_model(),
            "cores_available": cores,
            "shared": "yes: other jobs ran on the machine (see the load averages)",
        },
        "data": str(args.data) if args.data else f"dali synth kitti, {args.frames} frames, seed 0",
        "epochs": args.epochs,
        "global_batch": 2,
        "median_train_frames_per_s": medians,
        "ddp_2_over_serial_all_cores": round(medians["ddp-2"] / medians["serial-all-cores"], 3),
        "ddp_2_over_serial_1_thread": round(medians["ddp-2"] / medians["serial-1-thread"], 3),
        "runs": runs,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(document, indent=2) + "\n")
    print(json.dumps(document, indent=2))


if __name__ == "__main__":
    main()
