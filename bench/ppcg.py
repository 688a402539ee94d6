"""Benchmark: `dali ppcg-rc` / `ppcg-cf` seconds per frame (read + compute + write) on one core.

KITTI-like and nuScenes-like synthetic frames (dali synth scenes), their labeled cars jittered into
pseudo boxes (size +-6 %, centre +-0.15 m, yaw +-3 deg), a procedural CAD library and a point-model
library built from synthetic Waymo-like source frames. Runs the stage functions exactly as the CLI
does, pinned to one CPU core, and splits each frame's time into phases (read, points in boxes,
model selection, CF windows, ray set-up, Embree, assembling, writing, other) against the floor
of the same frames: reading and decoding the input bytes, the stage's own Embree calls replayed
bare, writing the output bytes (bench/pareto/ppcg_phases.py). Target: <= 3x the floor on KITTI. The paper's reference
(brute-force CUDA Moller-Trumbore on an RTX 3090): KITTI RC 0.40 s, CF 1.10 s; nuScenes 0.07 s,
0.27 s per frame. Writes bench/results/ppcg.json.

    .venv/bin/python bench/ppcg.py [--frames 40] [--library-cars 40] [--lod 20000] [--repeats 3]

Timings are medians of --repeats runs, with the machine, threads and load average recorded.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from pareto.common import load_average, machine, pin_one_core

RESULTS = Path(__file__).resolve().parent / "results" / "ppcg.json"
PAPER_S = {"kitti": {"rc": 0.40, "cf": 1.10}, "nuscenes": {"rc": 0.07, "cf": 0.27}}


def make_frames(directory: Path, sensor: str, frames: int, seed: int) -> dict:
    """Synthesize `frames` frames of `sensor` with jittered labels as pseudo boxes."""
    from pareto.data import jittered_frames

    from dali_cli.store.artifacts import BoxTable, FrameSetWriter, write_boxes, write_frameset

    made = jittered_frames(sensor, frames, seed)
    data = [(frame_id, points) for frame_id, points, _ in made]
    ids = [frame_id for frame_id, _, boxes in made for _ in range(len(boxes))]
    table = BoxTable.from_arrays(ids, np.concatenate([boxes for _, _, boxes in made]))
    write_frameset(directory, data, sensor=sensor)
    write_boxes(directory, table)
    # the same frames stored uncompressed, to show what reading zstd chunks costs
    raw = directory.parent / f"{directory.name}-uncompressed"
    raw.mkdir(parents=True, exist_ok=True)
    with FrameSetWriter(raw, sensor, compress=False) as writer:
        for frame_id, points in data:
            writer.append(frame_id, points)
    write_boxes(raw, table)
    return {
        "frames": frames,
        "points_per_frame": float(np.mean([len(p) for _, p in data])),
        "boxes_per_frame": float(np.mean([len(b) for _, _, b in made])),
    }


def make_library(directory: Path, cars: int, lod: int, source_frames: int) -> dict:
    """Procedural meshes plus point models from synthetic Waymo-like labeled frames."""
    from dali_cli.library import (
        PointModels,
        point_models_from_frame,
        procedural_library,
        write_library,
    )
    from dali_cli.sensors import get_profile
    from dali_cli.synth import synth_frame

    meshes = procedural_library(cars, seed=7, lod=lod)
    waymo = get_profile("waymo")
    parts = []
    for index in range(source_frames):
        frame = synth_frame(99, index, waymo, waymo)
        parts.append(point_models_from_frame(frame.points, frame.boxes, frame.frame_id, "waymo"))
    point_models = PointModels.concat(parts)
    directory.mkdir(parents=True, exist_ok=True)
    write_library(directory, meshes, point_models)
    return {
        "meshes": len(meshes),
        "mean_triangles": float(np.mean([m.num_triangles for m in meshes])),
        "point_models": len(point_models),
        "mean_points_per_point_model": float(np.mean(point_models.num_points))
        if len(point_models)
        else 0.0,
    }


def run_stage(mode: str, target: Path, library: Path, out: Path, models: str) -> dict:
    """One run of the stage as the CLI runs it, with its per-phase seconds and the floor of the
    same frames (bench/pareto/ppcg_phases.py)."""
    from pareto.ppcg_phases import Phases, floor_embree, floor_read, floor_write

    from dali_cli.store.artifacts import DEFAULT_CHUNK_POINTS, FrameSet
    from dali_cli.store.manifest import read_manifest
    from stages.ppcg_cf import ppcg_cf
    from stages.ppcg_rc import ppcg_rc

    function = ppcg_rc if mode == "rc" else ppcg_cf
    with Phases(record_traces=True) as phases:
        started = time.perf_counter()
        function(target, target, library, out, models=models, force=True, progress=False)
        wall = time.perf_counter() - started
    manifest = read_manifest(out)
    counts = manifest["outputs"]["counts"]
    frames = counts["frames"]
    stage_frames = manifest["timings"]["frames_seconds"]  # the frame loop: read, compute, write
    written, _ = FrameSet(out).load_all()
    measured = {
        "read": floor_read(target),
        "embree": floor_embree(phases.traces),
        "write": floor_write(written, DEFAULT_CHUNK_POINTS),
    }
    floor = {k: wall / frames for k, (wall, _) in measured.items()}
    floor["total"] = sum(floor.values())
    floor_cpu = {k: cpu / frames for k, (_, cpu) in measured.items()}
    floor_cpu["total"] = sum(floor_cpu.values())
    seconds = stage_frames / frames
    cpu_seconds = manifest["timings"]["cpu_seconds_per_frame"]
    return {
        "seconds_per_frame": round(seconds, 5),
        "cpu_seconds_per_frame": cpu_seconds,
        "read_compute_write_seconds_per_frame": [
            manifest["timings"][f"{part}_seconds_per_frame"]
            for part in ("read", "compute", "write")
        ],
        "phases_seconds_per_frame": phases.per_frame(frames, stage_frames),
        "phases_cpu_seconds_per_frame": phases.per_frame(
            frames, manifest["timings"]["frames_cpu_seconds"], cpu=True
        ),
        # compare with a run of another version: PPCG's speed work must not change one bit
        "points_sha256": hashlib.sha256(written.tobytes()).hexdigest(),
        "floor_seconds_per_frame": {k: round(v, 6) for k, v in floor.items()},
        "ratio_to_floor": round(seconds / floor["total"], 2),
        "floor_cpu_seconds_per_frame": {k: round(v, 6) for k, v in floor_cpu.items()},
        "cpu_ratio_to_floor": round(cpu_seconds / floor_cpu["total"], 2),
        "stage_wall_seconds_incl_library_load": round(wall, 3),
        "compute_seconds_per_frame": manifest["timings"]["compute_seconds_per_frame_with_boxes"],
        "embree_share_of_frame_loop": round(phases.seconds.get("embree", 0.0) / stage_frames, 3),
        "embree_seconds_per_frame": round(phases.seconds.get("embree", 0.0) / frames, 5),
        "rays_per_frame": round(phases.rays / frames, 1),
        "counts": counts,
    }


def median_run(runs: list[dict]) -> dict:
    """The run with the median frame-loop time; every run's time, floor and ratio kept."""
    ordered = sorted(runs, key=lambda r: r["seconds_per_frame"])
    middle = dict(ordered[(len(ordered) - 1) // 2])
    middle["all_runs_seconds_per_frame"] = [r["seconds_per_frame"] for r in runs]
    middle["all_runs_ratio_to_floor"] = [r["ratio_to_floor"] for r in runs]
    middle["all_runs_cpu_ratio_to_floor"] = [r["cpu_ratio_to_floor"] for r in runs]
    middle["median_cpu_ratio_to_floor"] = float(np.median([r["cpu_ratio_to_floor"] for r in runs]))
    middle["median_floor_seconds_per_frame"] = round(
        float(np.median([r["floor_seconds_per_frame"]["total"] for r in runs])), 6
    )
    return middle


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--library-cars", type=int, default=40)
    parser.add_argument("--lod", type=int, default=20000, help="triangles per procedural car")
    parser.add_argument("--source-frames", type=int, default=8, help="frames for point models")
    parser.add_argument(
        "--repeats", type=int, default=3, help="runs per stage; the median run is kept"
    )
    parser.add_argument(
        "--sensors", default="kitti,nuscenes", help="comma-separated target sensors to time"
    )
    parser.add_argument(
        "--data", default=None, help="keep the generated frames and library here and reuse them"
    )
    parser.add_argument("--results", default=str(RESULTS), help="where to write the JSON")
    args = parser.parse_args()
    pin_one_core()
    sensors = [s for s in args.sensors.split(",") if s]
    results = {
        "command": "python bench/ppcg.py " + " ".join(sys.argv[1:]),
        "machine": machine(threads=1),
        "load_average_at_start": load_average(),
        "repeats": args.repeats,
        "floor": "read (chunk bytes + CRC-32C + decode) + the stage's own Embree calls replayed "
        "bare + write (raw chunk bytes + CRC-32C), per frame; bench/pareto/ppcg_phases.py",
        "target_ratio_to_floor": 3.0,
        "paper_seconds_per_frame_rtx3090": PAPER_S,
        "targets_seconds_per_frame": {"rc": 0.01, "cf": 0.03},
    }
    with tempfile.TemporaryDirectory(prefix="dali-bench-ppcg-") as tmp:
        root = Path(args.data or tmp)
        key = f"v2-{args.frames}-{args.library_cars}-{args.lod}-{args.source_frames}"
        ready = root / f"ready-{key}.json"
        if args.data is not None and ready.is_file():
            made = json.loads(ready.read_text())
        else:
            made = {
                "library": make_library(
                    root / "library", args.library_cars, args.lod, args.source_frames
                )
            }
            for sensor in ("kitti", "nuscenes"):  # both, so --data stays reusable
                made[sensor] = make_frames(root / sensor, sensor, args.frames, seed=5)
            if args.data is not None:
                ready.write_text(json.dumps(made))
        results["library"] = made["library"]
        for sensor in sensors:
            section = {"data": made[sensor]}
            variants = [("cad", sensor), ("points", sensor), ("cad", f"{sensor}-uncompressed")]
            for models, frames_dir in variants:
                for mode in ("rc", "cf"):
                    runs = [
                        run_stage(
                            mode,
                            root / frames_dir,
                            root / "library",
                            root / f"{sensor}-{mode}",
                            models,
                        )
                        for _ in range(args.repeats)
                    ]
                    best = median_run(runs)
                    name = f"{mode}_{models}" + (
                        "_uncompressed_target" if frames_dir != sensor else ""
                    )
                    section[name] = best
                    print(
                        f"{sensor:9s} {name:27s}: {best['seconds_per_frame'] * 1e3:6.2f} ms/frame "
                        f"({best['cpu_seconds_per_frame'] * 1e3:.2f} ms CPU; read/compute/write "
                        f"{'/'.join(f'{v * 1e3:.1f}' for v in best['read_compute_write_seconds_per_frame'])}) "
                        f"(paper {PAPER_S[sensor][mode] * 1e3:.0f} ms on a GPU), Embree "
                        f"{best['embree_share_of_frame_loop'] * 100:.0f}%, {best['rays_per_frame']:.0f} rays/frame; "
                        f"floor {best['floor_seconds_per_frame']['total'] * 1e3:.2f} ms, "
                        f"{best['ratio_to_floor']:.2f}x floor (CPU {best['median_cpu_ratio_to_floor']:.2f}x)"
                    )
            results[sensor] = section
    results["load_average_at_end"] = load_average()
    targets = results["targets_seconds_per_frame"]
    if "kitti" in results:
        results["kitti_cad_meets_target"] = {
            f"{mode}_{clock}": results["kitti"][f"{mode}_cad"][key] <= targets[mode]
            for mode in ("rc", "cf")
            for clock, key in (("wall", "seconds_per_frame"), ("cpu", "cpu_seconds_per_frame"))
        }
        results["kitti_cad_within_3x_floor"] = {
            f"{mode}_{variant}_{clock}": results["kitti"][f"{mode}_{variant}"][key] <= 3.0
            for mode in ("rc", "cf")
            for variant in ("cad", "cad_uncompressed_target")
            for clock, key in (("wall", "ratio_to_floor"), ("cpu", "median_cpu_ratio_to_floor"))
        }
    path = Path(args.results)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
