"""Benchmark: `dali synth` frames per second on one core, per sensor profile.

For each profile: the one-off cost of the synthetic car pool (64 procedural cars and their BVHs,
built once per process), then frames/s of `synth_frame` (scene layout + full-pattern scan +
labels, one thread) and of the whole stage `build_synth` with one worker (including Zarr/Parquet
writes). Also the label statistics that show the domain gap (mean label size per --cars profile,
points per car by range band per sensor). Target: >= 5 KITTI-like frames/s on one core.

Writes bench/results/synth.json.   .venv/bin/python bench/synth.py [--frames 20]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results" / "synth.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20)
    args = parser.parse_args()

    from dali_cli import synth
    from dali_cli.sensors import get_profile
    from dali_cli.world import cars, scene

    started = time.perf_counter()
    for index in range(cars.POOL_SIZE):
        cars.pool_car(index).bvh()
    pool_seconds = time.perf_counter() - started

    result = {
        "machine": {
            "cores_available": len(os.sched_getaffinity(0)),
            "load_average_1m": os.getloadavg()[0],
        },
        "pool": {
            "cars": cars.POOL_SIZE,
            "triangles_each": cars.POOL_LOD,
            "build_seconds": round(pool_seconds, 2),
        },
        "profiles": {},
    }
    for name in ("kitti", "waymo", "nuscenes"):
        profile = get_profile(name)
        synth.synth_frame(0, 0, profile, profile)  # warm caches
        wall, cpu = time.perf_counter(), time.process_time()
        frames = [synth.synth_frame(1, k, profile, profile) for k in range(args.frames)]
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        with tempfile.TemporaryDirectory() as tmp:
            stage = time.perf_counter()
            synth.build_synth(tmp, profile, profile, args.frames, 1, progress=False)
            stage = time.perf_counter() - stage
        points = np.array([len(f.points) for f in frames])
        labels = np.concatenate([f.num_points for f in frames])
        distance = np.concatenate([np.hypot(f.boxes[:, 0], f.boxes[:, 1]) for f in frames])
        bands = {}
        for low, high in ((0, 20), (20, 40), (40, 80)):
            inside = (distance >= low) & (distance < high)
            bands[f"{low}-{high}m"] = (
                round(float(labels[inside].mean()), 1) if inside.any() else None
            )
        result["profiles"][name] = {
            "rays_per_frame": profile.num_rays,
            "frames": args.frames,
            "frames_per_second": round(args.frames / wall, 2),
            "frames_per_cpu_second": round(args.frames / cpu, 2),
            "stage_frames_per_second_1_worker": round(args.frames / stage, 2),
            "points_per_frame": int(points.mean()),
            "labels_per_frame": round(len(labels) / args.frames, 1),
            "mean_points_per_car_by_range": bands,
        }
    # the size gap: the same sensor, cars sized by different profiles (scenes only, no scan)
    sizes = {}
    kitti = get_profile("kitti")
    for name in ("kitti", "waymo", "nuscenes"):
        cars = get_profile(name)
        boxes = np.concatenate(
            [scene.generate_scene(synth.frame_rng(2, k), kitti, cars).cars for k in range(100)]
        )
        sizes[name] = {
            "mean_lwh_m": boxes[:, 3:6].mean(axis=0).round(3).tolist(),
            "profile_mean_lwh_m": list(cars.car_mean_lwh_m),
        }
    result["label_sizes_by_cars_profile"] = sizes
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
