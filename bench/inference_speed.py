"""Inference speed on real KITTI scans: the torch detector against onnxruntime (the same boxes),
and `dali detect` against `dali eval` on the same frames with the same model.

Writes bench/results/inference_speed.json. Run:
`.venv/bin/python bench/inference_speed.py --scans DIR [--model models/kitti-hdl64e]`, DIR a
folder of KITTI velodyne `.bin` scans (e.g. a KITTI object split's velodyne/). Frames/s are the
best of `--repeats` passes over the scans (wall clock); the CPU, threads and load average are
recorded with them, because the machines these runs share differ in speed.
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

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results" / "inference_speed.json"


def best_rate(run, frames: int, repeats: int) -> float:
    """Frames per second of the fastest of `repeats` calls of `run()` over `frames` frames."""
    best = min(_timed(run) for _ in range(repeats))
    return round(frames / best, 3)


def _timed(run) -> float:
    started = time.perf_counter()
    run()
    return time.perf_counter() - started


def cli_rate(args: list[str]) -> float:
    """Frames/s a dali command's manifest records (its stage wall time), one run."""
    out = Path(args[args.index("--out") + 1])
    subprocess.run([str(ROOT / ".venv" / "bin" / "dali"), *args, "--no-progress", "--force"],
                   check=True, capture_output=True)  # fmt: skip
    manifest = json.loads((out / "manifest.json").read_text())
    frames = manifest["outputs"]["counts"]["frames"]
    return round(frames / manifest["timings"]["wall_seconds"], 3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scans", type=Path, required=True)
    parser.add_argument("--model", type=Path, default=ROOT / "models" / "kitti-hdl64e")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()

    from dali_cli.detector import Detector
    from dali_cli.detector.onnx_export import OnnxDetector, export_onnx
    from dali_cli.runtime.machine import cpu_model
    from dali_cli.store.scale_file import read_scale

    paths = sorted(args.scans.glob("*.bin"))
    frames = [np.fromfile(p, "<f4").reshape(-1, 4) for p in paths]
    scale = read_scale(args.model).scale if (args.model / "scale.json").is_file() else 1.0
    detector = Detector.load(args.model)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        export_onnx(detector, tmp, scale)
        onnx = OnnxDetector(tmp)
        torch_rate = best_rate(
            lambda: detector.predict(frames, scale, 1.73), len(frames), args.repeats
        )
        onnx_rate = best_rate(lambda: onnx.predict(frames, 1.73), len(frames), args.repeats)
        imported = tmp / "imported"
        subprocess.run([str(ROOT / ".venv" / "bin" / "dali"), "import", "kitti", str(args.scans.parent.parent),
                        "--no-progress", "--out", str(imported)], check=True, capture_output=True)  # fmt: skip
        detect_rate = cli_rate(
            ["detect", str(args.scans), "--model", str(args.model), "--out", str(tmp / "d")]
        )
        eval_rate = cli_rate(["eval", "--model", str(args.model), "--data", str(imported),
                              "--scale-from", str(args.model), "--out", str(tmp / "e")])  # fmt: skip
    result = {
        "frames": len(frames),
        "model": str(
            args.model.relative_to(ROOT) if args.model.is_relative_to(ROOT) else args.model
        ),
        "torch_frames_per_s": torch_rate,
        "onnxruntime_frames_per_s": onnx_rate,
        "dali_detect_frames_per_s": detect_rate,
        "dali_eval_frames_per_s": eval_rate,
        "machine": {
            "cpu": cpu_model(),
            "cores": os.cpu_count(),
            "load_1min": round(os.getloadavg()[0], 2),
            "python": sys.version.split()[0],
        },  # fmt: skip
        "date": time.strftime("%Y-%m-%d"),
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
