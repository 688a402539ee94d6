"""Detector training front: pillar size -> AP_3D@0.7 vs training frames/s and inference s/frame.

Unlike the inference knobs (detector_front.py) a pillar size needs its own trained model, so this
front trains one per value, all on the same KITTI-like frames with their labels (an oracle: the
detector's capacity, not domain adaptation, is what is measured) and evaluates each on the same
validation frames at s = 1:

    equal frames  every pillar size trains `epochs` epochs (the same frames seen)
    equal time    the default size trains for as many epochs as the finest size needed seconds
                  (its frames/s measured in the equal-frames run), so the default's point says
                  whether it is on the front when a user spends the same training time

Everything runs through the `dali` CLI (pretrain --detector-config, eval), so a point is exactly
what a user gets; each point records its commands. Training and inference times come from the
stages' manifests (train_seconds; eval wall seconds / frames, model loading included).
"""

from __future__ import annotations

import json
from pathlib import Path

from dali_cli.reporting.report import read_kitti, read_metrics
from pareto.common import dali

PILLARS_M = (0.24, 0.40)  # swept around the detector's default, which is always a point


def _manifest(directory: Path) -> dict:
    return json.loads((directory / "manifest.json").read_text())


def train_and_evaluate(
    target: Path, target_val: Path, out: Path, pillar_m: float, epochs: int, seed: int, threads: int
) -> dict:
    """One point: train on `target`'s labels with this pillar size, evaluate on `target_val`."""
    out.mkdir(parents=True, exist_ok=True)
    config = out / "config.json"
    config.write_text(json.dumps({"pillar_m": pillar_m}) + "\n")
    model, evaluation = out / "model", out / "eval"
    commands = [
        dali("pretrain", "--source", target, "--epochs", epochs, "--seed", seed,
             "--threads", threads, "--no-progress", "--detector-config", config, "--out", model),
        dali("eval", "--model", model, "--data", target_val, "--scale", 1.0, "--protocol",
             "range", "--front-only", "--iou", 0.7, "--iou", 0.5, "--size-score-min", 0.3,
             "--workers", 1, "--out", evaluation),
        dali("eval", "--pred", evaluation / "predictions.parquet", "--gt", target_val,
             "--protocol", "kitti", "--iou", 0.7, "--size-score-min", 0.3,
             "--out", evaluation / "metrics_kitti.json"),
    ]  # fmt: skip
    training = _manifest(model)
    frames_seen = training["outputs"]["counts"]["frames_seen"]
    train_seconds = training["timings"]["train_seconds"]
    evaluated = _manifest(evaluation)
    val_frames = evaluated["outputs"]["counts"]["frames"]
    ap, _, _ = read_metrics(evaluation / "metrics.json")
    kitti = read_kitti(evaluation / "metrics_kitti.json")
    return {
        "pillar_m": pillar_m,
        "seed": seed,
        "epochs": epochs,
        "frames_seen": frames_seen,
        "train_seconds": round(train_seconds, 2),
        "training_frames_per_second": round(frames_seen / train_seconds, 3),
        "inference_seconds_per_frame": round(evaluated["timings"]["wall_seconds"] / val_frames, 4),
        "ap3d_07_all": ap["0.7"]["3d"],
        "ap_loss": 100.0 - ap["0.7"]["3d"],
        "ap3d_07_kitti_moderate": kitti["0.7"]["3d"]["moderate"],
        "threads": training["runtime"]["threads"],
        "commands": commands,
    }


def measure(
    target: Path, target_val: Path, run: Path, epochs: int, seeds=(0,), threads: int = 2,
    pillars=PILLARS_M, quick: bool = False,
) -> dict:  # fmt: skip
    """Equal-frames points for every pillar size and seed, then the default's equal-time point."""
    from dali_cli.detector.config import DetectorConfig

    default = DetectorConfig().pillar_m
    pillars = sorted({*pillars, default})
    pillars = (
        list(dict.fromkeys([pillars[0], default])) if quick else pillars
    )  # quick: finest, default
    points = []
    for seed in seeds:
        for pillar_m in pillars:
            point = train_and_evaluate(
                target, target_val, run / f"seed{seed}" / f"p{pillar_m:.2f}", pillar_m, epochs,
                seed, threads,
            )  # fmt: skip
            points.append({**point, "budget": "equal frames", "default": pillar_m == default})
        same_seed = [p for p in points if p["seed"] == seed]
        finest = min(same_seed, key=lambda p: p["pillar_m"])
        default_point = next(p for p in same_seed if p["pillar_m"] == default)
        if finest is default_point:
            continue
        # epochs the default needs to train as long as the finest size did (whole epochs)
        equal_epochs = max(
            epochs,
            round(finest["train_seconds"] * default_point["training_frames_per_second"]
                  / (default_point["frames_seen"] / epochs)),
        )  # fmt: skip
        point = train_and_evaluate(
            target, target_val, run / f"seed{seed}" / f"p{default:.2f}_equal_time", default,
            equal_epochs, seed, threads,
        )  # fmt: skip
        points.append({**point, "budget": "equal time", "default": False})
    return {
        "epochs": epochs,
        "seeds": list(seeds),
        "default_pillar_m": default,
        "points": points,
    }


def seed_means(points: list[dict]) -> list[dict]:
    """One point per (pillar size, budget): training seconds and AP loss averaged over seeds."""
    groups: dict[tuple, list[dict]] = {}
    for point in points:
        groups.setdefault((point["pillar_m"], point["budget"]), []).append(point)
    return [
        {
            "pillar_m": pillar_m,
            "budget": budget,
            "frames_seen": group[0]["frames_seen"],
            "seeds": len(group),
            "default": any(p["default"] for p in group),
            "train_seconds": sum(p["train_seconds"] for p in group) / len(group),
            "ap_loss": sum(p["ap_loss"] for p in group) / len(group),
        }
        for (pillar_m, budget), group in groups.items()
    ]
