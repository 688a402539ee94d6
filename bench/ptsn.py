"""Benchmark: PTSN bracket search vs the full grid on the synthetic Waymo-like -> KITTI-like task.

Measures, for the same model and target frames: detector frame passes, seconds and ŝ of
`--search bracket` and `--search grid` (0.8:1.4 step 0.01), |ŝ_bracket - ŝ_grid|; then the mean
pseudo-label size at ŝ vs E_est per dimension, and (when `dali eval` works) target AP at s = 1
(source only) and at ŝ. Targets: bracket <= 1/4 of the grid's frame passes with
|Δŝ| <= 0.01; mean pseudo-label size within 0.1 m of E_est per dimension.

Data and model: --model/--target/--target-val when given; else RUN/iter0/model and RUN/data/* of
`make experiment` (runs/experiment) when they exist; else they are built small under --run with
`dali synth` and `dali pretrain` (minutes). Writes bench/results/ptsn.json.

    .venv/bin/python bench/ptsn.py [--frames 100] [--run runs/bench_ptsn] [--minutes 8]
"""

from __future__ import annotations

import argparse
import json
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results" / "ptsn.json"
DALI = [sys.executable, "-m", "dali_cli.cli"]


def dali(*arguments, log: list) -> float:
    """Run one dali command (echoed, logged); returns wall seconds. Fails loudly."""
    command = [*DALI, *map(str, arguments)]
    shown = "dali " + " ".join(shlex.quote(str(a)) for a in arguments)
    print(f"$ {shown}", file=sys.stderr, flush=True)
    started = time.perf_counter()
    subprocess.run(command, check=True, cwd=ROOT)
    seconds = time.perf_counter() - started
    log.append({"command": shown, "seconds": round(seconds, 2)})
    return seconds


def ensure_inputs(args, log: list) -> tuple[Path, Path, Path | None]:
    """(model, target, target_val): given, reused from runs/experiment, or built under args.run."""
    if args.model and args.target:
        return (
            Path(args.model),
            Path(args.target),
            Path(args.target_val) if args.target_val else None,
        )
    experiment = ROOT / "runs" / "experiment"
    if (experiment / "iter0/model/manifest.json").is_file() and (
        experiment / "data/target/manifest.json"
    ).is_file():
        val = experiment / "data/target_val"
        return (
            experiment / "iter0/model",
            experiment / "data/target",
            val if (val / "manifest.json").is_file() else None,
        )
    run = Path(args.run)
    data = run / "data"
    jobs = [
        ("source", "waymo", args.train_frames, args.seed),
        ("target", "kitti", args.frames, args.seed + 1000),
        ("target_val", "kitti", args.val_frames, args.seed + 2000),
    ]
    for name, sensor, frames, seed in jobs:
        if not (data / name / "manifest.json").is_file():
            dali(
                "synth", "--sensor", sensor, "--cars", sensor, "--frames", frames, "--seed", seed,
                "--workers", 2, "--out", data / name, log=log,
            )  # fmt: skip
    model = run / "iter0/model"
    if not (model / "manifest.json").is_file():
        dali(
            "pretrain", "--source", data / "source", "--seed", args.seed, "--minutes", args.minutes,
            "--out", model, log=log,
        )  # fmt: skip
    return model, data / "target", data / "target_val"


def sweep(
    model: Path, target: Path, out: Path, search: str, args, log: list, match="volume"
) -> dict:
    seconds = dali(
        "ptsn-sweep", "--model", model, "--target", target, "--out", out, "--search", search,
        "--scales", args.scales, "--frames", args.frames, "--seed", args.seed, "--match", match,
        "--expected-size", "sn", "--plot", "--force", log=log,
    )  # fmt: skip
    document = json.loads((out / "scale.json").read_text())
    return {
        "scale": document["scale"],
        "clipped": document["clipped"],
        "fallback": document["fallback"],
        "monotone": document["monotone"],
        "scale_passes": document["passes"],
        "detector_frames": document["detector_frames"],
        "detector_seconds": document["detector_seconds"],
        "wall_seconds": round(seconds, 2),
        "E_est": document["E_est"],
        "E_pred_at_scale": document["E_pred_at_scale"],
        "bias_lwh": document["bias_lwh"],
        "frames": document["frames"],
    }


def evaluate(model: Path, data: Path, out: Path, scale: float, log: list) -> dict | None:
    """AP_BEV / AP_3D at 0.7 ("all" or "moderate") of `model` on `data` at `scale`, None if eval fails."""
    try:
        dali("eval", "--model", model, "--data", data, "--scale", scale, "--out", out, log=log)
    except subprocess.CalledProcessError:
        return None
    metrics = json.loads(out.read_text()).get("Car", {})
    pick = lambda table: table.get("all", table.get("moderate"))  # noqa: E731
    return {"bev": pick(metrics.get("bev", {})), "3d": pick(metrics.get("3d", {}))}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model")
    parser.add_argument("--target")
    parser.add_argument("--target-val")
    parser.add_argument("--run", default=str(ROOT / "runs" / "bench_ptsn"))
    parser.add_argument("--frames", type=int, default=100, help="target frames swept")
    parser.add_argument("--train-frames", type=int, default=300)
    parser.add_argument("--val-frames", type=int, default=100)
    parser.add_argument(
        "--minutes", type=float, default=8.0, help="pretrain budget when built here"
    )
    parser.add_argument("--scales", default="0.8:1.4:0.01")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-eval", action="store_true")
    args = parser.parse_args()

    log: list = []
    model, target, target_val = ensure_inputs(args, log)
    out = Path(args.run) / "ptsn"
    grid = sweep(model, target, out / "grid", "grid", args, log)
    bracket = sweep(model, target, out / "bracket", "bracket", args, log)
    bracket_lwh = sweep(model, target, out / "bracket_lwh", "bracket", args, log, match="lwh")
    dali(
        "pseudo-label", "--model", model, "--target", target, "--scale-from", out / "bracket",
        "--out", out / "pseudo", "--force", log=log,
    )  # fmt: skip
    summary = json.loads((out / "pseudo" / "summary.json").read_text())
    result = {
        "benchmark": "ptsn",
        "detector": "pillar-centerpoint-iou (dali's CPU stand-in for SECOND-IoU)",
        "model": str(model),
        "target": str(target),
        "scales": args.scales,
        "grid": grid,
        "bracket": bracket,
        "bracket_match_lwh": bracket_lwh,
        "frame_pass_ratio": round(bracket["detector_frames"] / grid["detector_frames"], 4),
        "abs_scale_difference": round(abs(bracket["scale"] - grid["scale"]), 5),
        "targets": {"frame_pass_ratio_max": 0.25, "abs_scale_difference_max": 0.01},
        "pseudo_labels": {
            "boxes": summary["boxes"],
            "boxes_per_frame": summary["boxes_per_frame"],
            "mean_lwh": summary["mean_lwh"],
            "E_est": summary["E_est"],
            "mean_minus_E_est": summary["mean_minus_E_est"],
            "target_abs_max_m": 0.1,
        },
        "machine": {"platform": platform.platform(), "python": platform.python_version()},
        "commands": log,
    }
    if target_val is not None and not args.no_eval:
        result["ap_at_0.7"] = {
            "source_only_s1": evaluate(model, target_val, out / "eval_s1.json", 1.0, log),
            "ptsn": evaluate(model, target_val, out / "eval_ptsn.json", bracket["scale"], log),
            "scale": bracket["scale"],
        }
    result["passed"] = bool(
        result["frame_pass_ratio"] <= 0.25
        and result["abs_scale_difference"] <= 0.01
        and summary["mean_minus_E_est"] is not None
        and max(abs(v) for v in summary["mean_minus_E_est"]) <= 0.1
    )
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(
        json.dumps({k: result[k] for k in ("frame_pass_ratio", "abs_scale_difference", "passed")})
    )


if __name__ == "__main__":
    main()
