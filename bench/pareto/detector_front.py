"""Detector front, inference-only knobs on one trained checkpoint: second stage (refiner) on/off,
bf16 autocast vs fp32, torch threads -> AP_3D@0.7 (all boxes of the range
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


def measure(
    model_dir, val_dir, sensor: str, quick: bool = False, frames=None, repeats: int = 1
) -> dict:
    """Every variant's AP (first run) and median seconds per frame over `repeats` runs; the
    variants run in turn within each repeat, so a slow minute of the machine hits them all."""
    import torch

    from dali_cli.detector import Detector
    from dali_cli.sensors import get_profile
    from dali_cli.store.artifacts import FrameSet, read_boxes

    detector = Detector.load(model_dir)
    base = detector.config
    frames = list(FrameSet(val_dir).iter_frames())[:frames]
    gt = read_boxes(val_dir)
    gt = gt.select(np.isin(gt.frame_id.astype(str), [frame_id for frame_id, _ in frames]))
    mount = get_profile(sensor).mount_height_m
    default_threads = torch.get_num_threads()
    defaults = {
        "refine": bool(base.refine),
        "precision": "fp32",
        "threads": default_threads,
    }
    variants = [dict(defaults)]
    for knob, values in (
        ("refine", [not defaults["refine"]]),
        ("precision", ["bf16"]),
        ("threads", [t for t in (1, 2) if t != default_threads]),
    ):
        variants += [{**defaults, knob: value} for value in values]
    variants.append({**defaults, "refine": False, "threads": 1})
    if quick:
        variants = variants[:2]
    seconds: dict[int, list[float]] = {index: [] for index in range(len(variants))}
    first: dict[int, dict] = {}
    try:
        for _ in range(max(1, repeats)):
            for index, variant in enumerate(variants):
                if index in first and "error" in first[index]:
                    continue
                detector.config = dataclasses.replace(base, refine=variant["refine"])
                torch.set_num_threads(variant["threads"])
                try:
                    took, results = _timed_predict(detector, frames, variant["precision"], mount)
                except Exception as error:  # a knob combination that does not run is a result
                    first[index] = {**variant, "default": False,
                                    "error": f"{type(error).__name__}: {error}"}  # fmt: skip
                    continue
                seconds[index].append(took / len(frames))
                if index not in first:
                    first[index] = _scored(variant, variant == defaults, frames, results, gt)
    finally:
        detector.config = base
        torch.set_num_threads(default_threads)
    points = []
    for index in range(len(variants)):
        point = first[index]
        if "error" not in point:
            point["seconds_per_frame"] = round(float(np.median(seconds[index])), 4)
            point["seconds_per_frame_runs"] = [round(value, 4) for value in seconds[index]]
        points.append(point)
    return {"frames": len(frames), "defaults": defaults, "repeats": repeats, "points": points}


def _timed_predict(detector, frames, precision: str, mount: float):
    import torch

    autocast = (
        torch.autocast("cpu", dtype=torch.bfloat16)
        if precision == "bf16"
        else contextlib.nullcontext()
    )
    started = time.perf_counter()
    with autocast:
        results = detector.predict([p for _, p in frames], mount_height_m=mount)
    return time.perf_counter() - started, results


def _scored(variant: dict, default: bool, frames, results, gt) -> dict:
    """The variant's AP_3D@0.7 (front region, all boxes; KITTI moderate) from its detections."""
    from dali_cli.evaluation.evaluate import evaluate
    from dali_cli.store.artifacts import BoxTable

    ids, boxes, scores = [], [], []
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
    return {
        **variant,
        "default": default,
        "ap3d_07_all": _ap(in_range, "all"),
        "ap3d_07_kitti_moderate": _ap(kitti, "moderate"),
    }
