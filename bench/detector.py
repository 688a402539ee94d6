"""Detector benchmarks (not tests).

  speed   inference s/frame on KITTI-like 64-beam frames and training frames/s, peak memory
          -> bench/results/detector.json
  oracle  train on labeled KITTI-like frames for a wall-clock budget, evaluating on held-out
          frames along the way (AP vs minutes) -> bench/results/detector_oracle.json

Usage:
  .venv/bin/python bench/detector.py speed [--data DIR] [--threads 2]
  .venv/bin/python bench/detector.py oracle --train DIR --val DIR --minutes 15 [--eval-every 2.5]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time
from pathlib import Path

import numpy as np
import torch

from dali_cli.artifacts import BoxTable, FrameSet, read_boxes
from dali_cli.detector import (
    Augmentation,
    Detector,
    DetectorConfig,
    PillarCenterNet,
    TrainSettings,
    load_labeled,
    train,
)
from dali_cli.detector.augment import ObjectDatabase
from dali_cli.detector.data import detection_region
from dali_cli.detector.toy import place_cars, scan
from dali_cli.sensors import get_profile

RESULTS = Path(__file__).resolve().parent / "results"


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def kitti_frames(data: str | None, count: int) -> list[np.ndarray]:
    """`count` sensor-frame KITTI-like frames: from a FrameSet, or toy scenes (full 360° scan)."""
    if data:
        frames = FrameSet(data)
        return [frames.frame(i) for i in range(min(count, len(frames)))]
    profile = get_profile("kitti")
    out = []
    for i in range(count):
        boxes = place_cars(
            np.random.default_rng(i), 15, profile.car_mean_lwh_m, profile.mount_height_m
        )
        out.append(scan(boxes, profile, azimuth_range_deg=(-180.0, 180.0)))
    return out


def bench_speed(args) -> dict:
    torch.set_num_threads(args.threads)
    config = DetectorConfig()
    torch.manual_seed(0)
    net = PillarCenterNet(config).eval()
    detector = Detector(net)
    detector.config.score_threshold = 0.0  # decode + NMS the full top-k: the slowest case
    frames = kitti_frames(args.data, 12)
    detector.predict(frames[:2])  # warm-up
    timings = []
    for frame in frames:
        started = time.perf_counter()
        detector.predict([frame])
        timings.append(time.perf_counter() - started)
    result = {
        "device": f"CPU, {args.threads} torch threads",
        "load_average_1min": os.getloadavg()[0],
        "points_per_frame": float(np.mean([len(f) for f in frames])),
        "inference_s_per_frame_median": float(np.median(timings)),
        "inference_s_per_frame_min": float(np.min(timings)),
    }
    # training throughput on labeled frames (toy scans as labels when no data is given)
    profile = get_profile("kitti")
    if args.data:
        data = load_labeled(args.data, config)
        data.points, data.boxes, data.frame_ids = (
            data.points[:16],
            data.boxes[:16],
            data.frame_ids[:16],
        )
    else:
        from dali_cli.detector.data import LabeledFrames

        points, boxes = [], []
        for i, frame in enumerate(frames):
            b = place_cars(
                np.random.default_rng(i), 15, profile.car_mean_lwh_m, profile.mount_height_m
            )
            ground = frame.copy()
            ground[:, 2] += profile.mount_height_m
            b[:, 2] += profile.mount_height_m
            points.append(ground)
            boxes.append(b)
        data = LabeledFrames(
            "toy",
            "kitti",
            profile.mount_height_m,
            [str(i) for i in range(len(frames))],
            points,
            boxes,
        )
    data.database = ObjectDatabase.build(data.points, data.boxes, region=detection_region(config))
    train_net = PillarCenterNet(config)
    settings = TrainSettings(epochs=1.0, batch_size=2, threads=args.threads, log_every=1)
    warm = TrainSettings(epochs=0.25, batch_size=2, threads=args.threads, log_every=1)
    train(train_net, [data], [Augmentation()], warm, progress=False)
    outcome = train(train_net, [data], [Augmentation()], settings, progress=False)
    result["train_frames_per_s"] = outcome.frames / outcome.seconds
    result["train_frames"] = outcome.frames
    result["peak_rss_mb"] = peak_rss_mb()
    result["load_average_1min_end"] = os.getloadavg()[0]
    return result


def bench_oracle(args) -> dict:
    from dali_cli.evaluate import evaluate

    torch.set_num_threads(args.threads)
    config = DetectorConfig.from_dict(json.loads(args.config)) if args.config else DetectorConfig()
    started = time.perf_counter()
    data = load_labeled(args.train, config)
    config.sensor, config.mount_height_m = data.sensor, data.mount_height_m
    data.database = ObjectDatabase.build(data.points, data.boxes, region=detection_region(config))
    load_s = time.perf_counter() - started
    val = FrameSet(args.val)
    val_frames = [points for _, points in val.iter_frames()]
    gt = read_boxes(args.val)
    torch.manual_seed(args.seed)
    net = PillarCenterNet(config)
    detector = Detector(net)
    curve, next_eval = [], args.eval_every * 60

    def evaluate_now(elapsed_s: float) -> dict:
        net.eval()
        started = time.perf_counter()
        predictions = detector.predict(val_frames, mount_height_m=data.mount_height_m)
        infer_s = (time.perf_counter() - started) / len(val_frames)
        ids = [
            fid
            for fid, (b, _) in zip(val.frame_ids, predictions, strict=True)
            for _ in range(len(b))
        ]
        pred = BoxTable.from_arrays(
            np.asarray(ids, dtype=str),
            np.concatenate([b for b, _ in predictions]),
            score=np.concatenate([s for _, s in predictions]),
        )
        point = {"minutes": round(elapsed_s / 60, 2), "val_infer_s_per_frame": round(infer_s, 4)}
        variants = {"st3d": ("st3d", 0), "st3d_min10pts": ("st3d", 10), "range": ("range", 0)}
        for name, (protocol, min_points) in variants.items():
            for iou in (0.7, 0.5):
                metrics = evaluate(
                    pred,
                    gt,
                    iou=iou,
                    protocol=protocol,
                    min_gt_points=min_points,
                    frame_ids=list(val.frame_ids),
                )["Car"]
                band = "moderate" if protocol == "st3d" else "all"
                point[f"{name}_bev@{iou}"] = round(metrics["bev"][band], 2)
                point[f"{name}_3d@{iou}"] = round(metrics["3d"][band], 2)
        sizes = pred.boxes[pred["score"] >= 0.3, 3:6]
        point["pred_mean_lwh@0.3"] = (
            [round(v, 3) for v in sizes.mean(axis=0).tolist()] if len(sizes) else None
        )
        net.train()
        print(json.dumps(point), flush=True)
        return point

    def on_log(row):
        nonlocal next_eval
        if row["elapsed_s"] >= next_eval:
            curve.append(evaluate_now(row["elapsed_s"]))
            next_eval += args.eval_every * 60

    settings = TrainSettings(
        minutes=args.minutes,
        batch_size=args.batch_size,
        lr=args.lr,
        seed=args.seed,
        threads=args.threads,
    )
    outcome = train(net, [data], [Augmentation()], settings, progress=True, on_log=on_log)
    curve.append(evaluate_now(outcome.seconds))
    if args.save:
        from dali_cli.detector import save_checkpoint

        Path(args.save).mkdir(parents=True, exist_ok=True)
        save_checkpoint(
            args.save,
            net,
            {"provenance": {"stage": "bench/detector.py oracle", "train": str(args.train)}},
        )
    return {
        "detector": "pillar-centerpoint-iou (dali), fp32",
        "config_overrides": json.loads(args.config) if args.config else {},
        "train": str(args.train),
        "val": str(args.val),
        "train_frames": len(data),
        "train_boxes": data.num_boxes,
        "val_frames": len(val),
        "minutes_budget": args.minutes,
        "steps": outcome.steps,
        "frames_seen": outcome.frames,
        "train_seconds": round(outcome.seconds, 1),
        "load_seconds": round(load_s, 1),
        "threads": args.threads,
        "load_average_1min_end": os.getloadavg()[0],
        "curve": curve,
        "final": curve[-1],
        "peak_rss_mb": peak_rss_mb(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="mode", required=True)
    speed = sub.add_parser("speed")
    speed.add_argument("--data", default=None, help="KITTI-like FrameSet (default: toy scans)")
    speed.add_argument("--threads", type=int, default=2)
    oracle = sub.add_parser("oracle")
    oracle.add_argument("--train", required=True)
    oracle.add_argument("--val", required=True)
    oracle.add_argument("--minutes", type=float, default=15.0)
    oracle.add_argument(
        "--eval-every", type=float, default=2.5, help="minutes of training between evaluations"
    )
    oracle.add_argument("--batch-size", type=int, default=2)
    oracle.add_argument("--lr", type=float, default=3e-3)
    oracle.add_argument("--seed", type=int, default=0)
    oracle.add_argument("--threads", type=int, default=2)
    oracle.add_argument("--out", default=None)
    oracle.add_argument("--config", default=None, help="JSON object of DetectorConfig overrides")
    oracle.add_argument(
        "--save", default=None, help="also write the trained model (model.pt + model.json) here"
    )
    args = parser.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    if args.mode == "speed":
        result, name = bench_speed(args), "detector.json"
    else:
        result, name = bench_oracle(args), "detector_oracle.json"
    path = Path(args.out) if getattr(args, "out", None) else RESULTS / name
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "curve"}, indent=2))


if __name__ == "__main__":
    main()
