"""Detector benchmarks (not tests).

  speed   inference s/frame on KITTI-like 64-beam frames and training frames/s, peak memory
          -> bench/results/detector.json
  oracle  train on labeled KITTI-like frames for a wall-clock budget, evaluating on held-out
          frames along the way (AP vs minutes) -> bench/results/detector_oracle.json
  decode  one checkpoint scored with several decoding settings -> detector_decode.json
  errors  where a checkpoint's 3D boxes miss: per-parameter errors of matched detections and the
          share above 3D IoU 0.7 with each parameter set to the truth -> detector_errors.json

Usage:
  .venv/bin/python bench/detector.py speed [--data DIR] [--threads 2]
  .venv/bin/python bench/detector.py oracle --train DIR --val DIR --minutes 15 [--eval-every 2.5]
  .venv/bin/python bench/detector.py errors --model DIR --val DIR
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch

from dali_cli.detector.augment import ObjectDatabase
from dali_cli.detector.config import DetectorConfig
from dali_cli.detector.data import Augmentation, detection_region, load_labeled
from dali_cli.detector.infer import Detector
from dali_cli.detector.model import PillarCenterNet
from dali_cli.detector.train import TrainSettings, train
from dali_cli.runtime.machine import cpu_model
from dali_cli.sensors import get_profile
from dali_cli.store.artifacts import BoxTable, FrameSet, read_boxes

RESULTS = Path(__file__).resolve().parent / "results"
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))  # the toy scenes
from toy_scenes import place_cars, scan  # noqa: E402  (a test fixture, not part of the package)


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
    detector = Detector(net, precision=args.precision)
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
        "precision": args.precision,
        "cpu_model": cpu_model(),
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
    setup = dict(
        batch_size=args.batch_size,
        threads=args.train_threads or args.threads,
        precision=args.precision,
    )
    settings = TrainSettings(epochs=args.epochs, log_every=1, **setup)
    warm = TrainSettings(epochs=0.25, log_every=1, **setup)
    train(train_net, [data], [Augmentation()], warm, progress=False)
    outcome = train(train_net, [data], [Augmentation()], settings, progress=False)
    result["train_frames_per_s"] = outcome.frames / outcome.seconds
    result["train_frames"] = outcome.frames
    result["train_setup"] = setup
    result["peak_rss_mb"] = peak_rss_mb()
    result["load_average_1min_end"] = os.getloadavg()[0]
    return result


def score_val_set(detector, val, val_frames, gt, mount_height_m: float) -> dict:
    """AP_BEV / AP_3D at IoU 0.7 and 0.5 on a labeled val set (protocols st3d, st3d with >= 10
    points, range, and kitti's moderate when the labels carry KITTI difficulty fields), the
    inference time per frame and the mean predicted size at score >= 0.3."""
    from dali_cli.evaluation.evaluate import evaluate, has_kitti_columns

    started = time.perf_counter()
    predictions = detector.predict(val_frames, mount_height_m=mount_height_m)
    infer_s = (time.perf_counter() - started) / len(val_frames)
    ids = [
        fid for fid, (b, _) in zip(val.frame_ids, predictions, strict=True) for _ in range(len(b))
    ]
    pred = BoxTable.from_arrays(
        np.asarray(ids, dtype=str),
        np.concatenate([b for b, _ in predictions]),
        score=np.concatenate([s for _, s in predictions]),
    )
    point = {"val_infer_s_per_frame": round(infer_s, 4)}
    variants = {"st3d": ("st3d", 0), "st3d_min10pts": ("st3d", 10), "range": ("range", 0)}
    if has_kitti_columns(gt):
        variants["kitti"] = ("kitti", 0)
    for name, (protocol, min_points) in variants.items():
        for iou in (0.7, 0.5):
            metrics = evaluate(
                pred,
                gt,
                iou=iou,
                protocol=protocol,
                min_gt_points=min_points,
                frame_ids=list(val.frame_ids),
                front_only=protocol == "kitti",
            )["Car"]
            band = "moderate" if protocol in ("st3d", "kitti") else "all"
            point[f"{name}_bev@{iou}"] = round(metrics["bev"][band], 2)
            point[f"{name}_3d@{iou}"] = round(metrics["3d"][band], 2)
    sizes = pred.boxes[pred["score"] >= 0.3, 3:6]
    point["pred_mean_lwh@0.3"] = (
        [round(v, 3) for v in sizes.mean(axis=0).tolist()] if len(sizes) else None
    )
    point["boxes@0.3"] = int(len(sizes))
    point["boxes@0.3_on_no_label"] = unlabeled_detections(pred.select(pred["score"] >= 0.3), gt)
    return point


def unlabeled_detections(pred: BoxTable, gt: BoxTable) -> int:
    """Predictions that overlap no label of their frame at all (BEV IoU 0): what a pseudo-label
    threshold would pass on as false cars."""
    from dali_cli.geometry import bev_iou

    rows = gt.rows_by_frame()
    count = 0
    for frame_id, index in pred.rows_by_frame().items():
        boxes = pred.select(index).boxes
        labels = gt.select(rows.get(frame_id, np.zeros(0, np.int64))).boxes
        overlap = bev_iou(boxes, labels).max(axis=1) if len(labels) else np.zeros(len(boxes))
        count += int((overlap <= 0).sum())
    return count


def bench_decode(args) -> dict:
    """One checkpoint scored with several decoding settings (e.g. iou_alpha)."""
    import dataclasses

    torch.set_num_threads(args.threads)
    detector = Detector.load(args.model)
    base = detector.config
    val = FrameSet(args.val)
    val_frames = [points for _, points in val.iter_frames()]
    gt = read_boxes(args.val)
    mount = get_profile(val.sensor).mount_height_m
    rows = []
    for overrides in json.loads(args.variants):
        detector.config = dataclasses.replace(base, **overrides)
        row = {"overrides": overrides, **score_val_set(detector, val, val_frames, gt, mount)}
        print(json.dumps(row), flush=True)
        rows.append(row)
    return {"model": str(args.model), "val": str(args.val), "variants": rows}


def bench_oracle(args) -> dict:
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
        point = {"minutes": round(elapsed_s / 60, 2)}
        point.update(score_val_set(detector, val, val_frames, gt, data.mount_height_m))
        net.train()
        print(json.dumps(point), flush=True)
        return point

    def on_log(row):
        nonlocal next_eval
        if row["elapsed_s"] >= next_eval:
            curve.append(evaluate_now(row["elapsed_s"]))
            next_eval += args.eval_every * 60

    settings = TrainSettings(
        minutes=None if args.epochs else args.minutes,
        epochs=args.epochs or 0.0,
        batch_size=args.batch_size,
        lr=args.lr,
        seed=args.seed,
        threads=args.threads,
        pct_start=args.pct_start,
    )
    augmentation = Augmentation(**json.loads(args.augment)) if args.augment else Augmentation()
    outcome = train(net, [data], [augmentation], settings, progress=True, on_log=on_log)
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
        "detector": f"{config.name} (dali), fp32",
        "config_overrides": json.loads(args.config) if args.config else {},
        "augmentation_overrides": json.loads(args.augment) if args.augment else {},
        "batch_size": args.batch_size,
        "lr": args.lr,
        "seed": args.seed,
        "pct_start": args.pct_start,
        "train": str(args.train),
        "val": str(args.val),
        "train_frames": len(data),
        "train_boxes": data.num_boxes,
        "val_frames": len(val),
        "minutes_budget": None if args.epochs else args.minutes,
        "epochs_budget": args.epochs,
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


def match_detections(
    predictions: list[tuple[np.ndarray, np.ndarray]], truth: list[np.ndarray], min_bev_iou: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Greedy one-to-one matches (best BEV IoU first) per frame: matched ground truth (N, 7),
    predictions (N, 7), their scores (N,) and the index (N,) of each match's ground truth in the
    concatenated truth."""
    from dali_cli.geometry import bev_iou

    gt_rows, pred_rows, scores_kept, gt_index, offset = [], [], [], [], 0
    for (boxes, scores), gt in zip(predictions, truth, strict=True):
        if len(gt) and len(boxes):
            iou = bev_iou(gt, boxes)  # (G, P)
            used = np.zeros(len(boxes), bool)
            for g in np.argsort(-iou.max(axis=1)):
                p = int(np.argmax(np.where(used, -1.0, iou[g])))
                if iou[g, p] > min_bev_iou and not used[p]:  # all used: argmax hits a used one
                    used[p] = True
                    gt_rows.append(gt[g])
                    pred_rows.append(boxes[p])
                    scores_kept.append(scores[p])
                    gt_index.append(offset + g)
        offset += len(gt)
    return (
        np.asarray(gt_rows).reshape(-1, 7),
        np.asarray(pred_rows).reshape(-1, 7),
        np.asarray(scores_kept, np.float64),
        np.asarray(gt_index, np.int64),
    )


def bench_errors(args) -> dict:
    """Error breakdown of matched detections (score >= --score-min) in the st3d region."""
    from dali_cli.evaluation.evaluate import in_st3d_region
    from dali_cli.geometry import iou_3d_pairs

    torch.set_num_threads(args.threads)
    detector = Detector.load(args.model)
    val, gt = FrameSet(args.val), read_boxes(args.val)
    rows = gt.rows_by_frame()
    predictions, truth, points_on_car = [], [], []
    for frame_id, points in val.iter_frames():
        boxes, scores = detector.predict([points])[0]
        predictions.append((boxes[scores >= args.score_min], scores[scores >= args.score_min]))
        table = gt.select(rows.get(frame_id, np.zeros(0, np.int64)))
        table = table.select((table["label"].astype(str) == "Car") & in_st3d_region(table))
        truth.append(table.boxes)
        points_on_car.append(np.asarray(table["num_points"]))
    gt_boxes, pred_boxes, scores, index = match_detections(predictions, truth, 0.3)
    if len(index) < 2:
        raise SystemExit(f"{args.model}: fewer than 2 detections match the ground truth")
    counts = np.concatenate(points_on_car)[index]
    error = pred_boxes - gt_boxes
    yaw = (error[:, 6] + np.pi / 2) % np.pi - np.pi / 2  # a box turned by 180 deg is the same
    radius = np.hypot(gt_boxes[:, 0], gt_boxes[:, 1])
    ux, uy = gt_boxes[:, 0] / radius, gt_boxes[:, 1] / radius
    parts = {
        "radial_m": error[:, 0] * ux + error[:, 1] * uy,
        "tangential_m": -error[:, 0] * uy + error[:, 1] * ux,
        "z_m": error[:, 2],
        "l_m": error[:, 3],
        "w_m": error[:, 4],
        "h_m": error[:, 5],
        "yaw_deg": np.degrees(yaw),
    }
    iou = iou_3d_pairs(pred_boxes, gt_boxes)
    with_truth = {}
    for name, columns in {
        "xy": [0, 1], "z": [2], "lw": [3, 4], "h": [5], "zh": [2, 5], "yaw": [6], "lwh": [3, 4, 5],
    }.items():  # fmt: skip
        fixed = pred_boxes.copy()
        fixed[:, columns] = gt_boxes[:, columns]
        with_truth[name] = round(float((iou_3d_pairs(fixed, gt_boxes) >= 0.7).mean()), 3)
    bands = {}
    for low, high in ((0, 10), (10, 30), (30, 100), (100, None)):
        band = (counts >= low) & (counts < (high or np.inf))
        stats = {"matches": int(band.sum())}
        if band.any():
            stats["share_iou3d_ge_0.7"] = round(float((iou[band] >= 0.7).mean()), 3)
            stats["mean_abs_z_m"] = round(float(np.abs(error[band, 2]).mean()), 3)
            stats["mean_abs_h_m"] = round(float(np.abs(error[band, 5]).mean()), 3)
        bands[f"{low}-{high or 'inf'} points"] = stats
    return {
        "model": str(args.model),
        "val": str(args.val),
        "score_min": args.score_min,
        "ground_truth": int(sum(len(t) for t in truth)),
        "matches": len(iou),
        "mean": {k: round(float(v.mean()), 3) for k, v in parts.items()},
        "mean_abs": {k: round(float(np.abs(v).mean()), 3) for k, v in parts.items()},
        "median_abs": {k: round(float(np.median(np.abs(v))), 3) for k, v in parts.items()},
        "share_iou3d_ge_0.7": round(float((iou >= 0.7).mean()), 3),
        "share_iou3d_ge_0.7_with_true": with_truth,
        "score_iou_correlation": round(float(np.corrcoef(scores, iou)[0, 1]), 3),
        "by_points_on_car": bands,
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="mode", required=True)
    speed = sub.add_parser("speed")
    speed.add_argument("--data", default=None, help="KITTI-like FrameSet (default: toy scans)")
    speed.add_argument("--threads", type=int, default=2)
    speed.add_argument("--train-threads", type=int, default=None, help="(default: --threads)")
    speed.add_argument("--batch-size", type=int, default=1)
    speed.add_argument("--epochs", type=float, default=4.0, help="passes over the 16 frames")
    speed.add_argument(
        "--precision",
        choices=["fp32", "bf16"],
        default="fp32",
        help="bf16 autocast in inference and training (a CPU with AVX512-BF16 or AMX)",
    )
    speed.add_argument("--out", default=None)
    oracle = sub.add_parser("oracle")
    oracle.add_argument("--train", required=True)
    oracle.add_argument("--val", required=True)
    oracle.add_argument("--minutes", type=float, default=15.0)
    oracle.add_argument(
        "--epochs",
        type=float,
        default=None,
        help="a step budget instead of --minutes (passes over the training set): results that do "
        "not depend on the machine's load, for ablations",
    )
    oracle.add_argument(
        "--eval-every", type=float, default=2.5, help="minutes of training between evaluations"
    )
    oracle.add_argument("--batch-size", type=int, default=1)
    oracle.add_argument("--lr", type=float, default=5e-3)
    oracle.add_argument("--seed", type=int, default=0)
    oracle.add_argument(
        "--pct-start", type=float, default=0.3, help="warm-up share of the one-cycle schedule"
    )
    oracle.add_argument("--threads", type=int, default=2)
    oracle.add_argument("--out", default=None)
    oracle.add_argument("--config", default=None, help="JSON object of DetectorConfig overrides")
    oracle.add_argument(
        "--augment",
        default=None,
        help="JSON object of Augmentation overrides, e.g. gt_sample_count",
    )
    oracle.add_argument(
        "--save", default=None, help="also write the trained model (model.pt + model.json) here"
    )
    decode = sub.add_parser("decode")
    decode.add_argument("--model", required=True, help="checkpoint directory")
    decode.add_argument("--val", required=True, help="labeled KITTI-like FrameSet")
    decode.add_argument(
        "--variants",
        default='[{}, {"iou_alpha": 0.8}]',
        help="JSON list of DetectorConfig overrides, one evaluation each",
    )
    decode.add_argument("--threads", type=int, default=2)
    decode.add_argument("--out", default=None)
    errors = sub.add_parser("errors")
    errors.add_argument("--model", required=True, help="checkpoint directory")
    errors.add_argument("--val", required=True, help="labeled KITTI-like FrameSet")
    errors.add_argument("--score-min", type=float, default=0.3)
    errors.add_argument("--threads", type=int, default=2)
    errors.add_argument("--out", default=None)
    args = parser.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    if args.mode == "speed":
        result, name = bench_speed(args), "detector.json"
    elif args.mode == "decode":
        result, name = bench_decode(args), "detector_decode.json"
    elif args.mode == "errors":
        result, name = bench_errors(args), "detector_errors.json"
    else:
        result, name = bench_oracle(args), "detector_oracle.json"
    path = Path(args.out) if getattr(args, "out", None) else RESULTS / name
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "curve"}, indent=2))


if __name__ == "__main__":
    main()
