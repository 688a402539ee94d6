"""Detector front, inference-only knobs on one trained checkpoint: second stage (refiner) on/off,
test-time flip on/off, bf16 autocast vs fp32, torch threads -> AP_3D@0.7 (all boxes of the range
protocol, and KITTI moderate) vs inference seconds per frame.

Knobs that need a model trained for each value (pillar size; training frames/s) are the pillar
front's (pillar_front.py).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time

import numpy as np


def _ap(metrics: dict, key: str) -> float | None:
    value = metrics["Car"]["3d"][key]
    return None if value is None else float(value)


def measure(model_dir, val_dir, sensor: str, quick: bool = False, frames=None) -> dict:
    import torch

    from dali_cli.artifacts import BoxTable, FrameSet, read_boxes
    from dali_cli.detector import Detector
    from dali_cli.evaluate import evaluate
    from dali_cli.sensors import get_profile

    detector = Detector.load(model_dir)
    base = detector.config
    frames = list(FrameSet(val_dir).iter_frames())[:frames]
    gt = read_boxes(val_dir)
    gt = gt.select(np.isin(gt.frame_id.astype(str), [frame_id for frame_id, _ in frames]))
    mount = get_profile(sensor).mount_height_m
    default_threads = torch.get_num_threads()
    defaults = {
        "refine": bool(base.refine),
        "flip_test": bool(base.flip_test),
        "precision": "fp32",
        "threads": default_threads,
    }
    variants = [dict(defaults)]
    for knob, values in (
        ("refine", [not defaults["refine"]]),
        ("flip_test", [not defaults["flip_test"]]),
        ("precision", ["bf16"]),
        ("threads", [t for t in (1, 2) if t != default_threads]),
    ):
        variants += [{**defaults, knob: value} for value in values]
    variants.append({**defaults, "refine": False, "flip_test": False, "threads": 1})
    if quick:
        variants = variants[:2]
    points = []
    try:
        for variant in variants:
            detector.config = dataclasses.replace(
                base, refine=variant["refine"], flip_test=variant["flip_test"]
            )
            torch.set_num_threads(variant["threads"])
            autocast = (
                torch.autocast("cpu", dtype=torch.bfloat16)
                if variant["precision"] == "bf16"
                else contextlib.nullcontext()
            )
            ids, boxes, scores = [], [], []
            started = time.perf_counter()
            try:
                with autocast:
                    results = detector.predict([p for _, p in frames], mount_height_m=mount)
            except Exception as error:  # a knob combination that does not run is a result too
                points.append(
                    {**variant, "default": False, "error": f"{type(error).__name__}: {error}"}
                )
                continue
            seconds = (time.perf_counter() - started) / len(frames)
            for (frame_id, _), (frame_boxes, frame_scores) in zip(frames, results, strict=True):
                ids += [frame_id] * len(frame_boxes)
                boxes.append(frame_boxes)
                scores.append(frame_scores)
            pred = BoxTable.from_arrays(
                ids, np.concatenate(boxes), score=np.concatenate(scores).astype(np.float32)
            )
            frame_ids = [frame_id for frame_id, _ in frames]
            in_range = evaluate(
                pred, gt, iou=0.7, protocol="range", frame_ids=frame_ids, front_only=True
            )  # the experiment's protocol: front region, detection range
            kitti = evaluate(pred, gt, iou=0.7, protocol="kitti", frame_ids=frame_ids)
            points.append(
                {
                    **variant,
                    "default": variant == defaults,
                    "seconds_per_frame": round(seconds, 4),
                    "ap3d_07_all": _ap(in_range, "all"),
                    "ap3d_07_kitti_moderate": _ap(kitti, "moderate"),
                }
            )
    finally:
        detector.config = base
        torch.set_num_threads(default_threads)
    return {"frames": len(frames), "defaults": defaults, "points": points}
