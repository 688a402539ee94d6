"""Benchmark: run time against error for every stage's speed knobs, defaults marked.

Fronts (each point a measured (seconds, error) pair on the same data; bench/pareto/*_front.py
says how each is measured):

    raycast   Embree robust vs fast, float64 vs float32 ray set-up -> hit error vs rays/s
    ppcg      mesh detail, library size -> surface / box-fit / size-fit error vs ms/frame;
              CF angular window on/off (identical points, rays saved); skips
    ptsn      grid step, bracket vs grid, frame subsample -> |ŝ - ŝ_ref| vs passes and seconds
    detector  second stage, bf16, threads -> AP_3D@0.7 vs inference s/frame
    pillar    pillar size (a model trained per value, equal frames and equal time) -> AP_3D@0.7
              vs training seconds (training frames/s and inference s/frame in the table)

The PTSN and detector fronts need a trained model and KITTI-like target frames: --model,
--target, --target-val, or they are built under --run (dali synth + dali pretrain, minutes). The
pillar front trains its own models on --target's labels under --run/pillar (~7 min idle, 2 cores;
finished points are reused: each stage skips itself when up to date).
Writes bench/results/pareto.json and docs/pareto/*.png (docs/pareto.md explains them). Timings
are medians of --repeats runs with the machine, threads and load average recorded; the machine
is usually shared, so compare points of one run, not runs.

    .venv/bin/python bench/pareto.py [--quick] [--only raycast,ppcg,ptsn,detector,pillar]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from importlib import import_module
from pathlib import Path

from pareto.common import dali, load_average, machine

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results" / "pareto.json"
PLOTS = ROOT / "docs" / "pareto"
FRONTS = ("raycast", "ppcg", "ptsn", "detector", "pillar")


def ensure_model(args) -> tuple[Path, Path, Path, list[str]]:
    """(model, target, target_val, commands): given, or built small under args.run."""
    if args.model and args.target and args.target_val:
        return Path(args.model), Path(args.target), Path(args.target_val), []
    run = Path(args.run)
    frames = 16 if args.quick else 40
    jobs = [
        ("source", "waymo", 24 if args.quick else 48, 0),
        ("target", "kitti", frames, 1000),
        ("target_val", "kitti", frames, 2000),
    ]
    commands = []
    for name, sensor, count, seed in jobs:
        out = run / name
        command = ["synth", "--sensor", sensor, "--cars", sensor, "--frames", count, "--seed", seed]
        command += ["--workers", 1, "--out", out]
        commands.append("dali " + " ".join(map(str, command)))
        if not (out / "manifest.json").is_file():
            dali(*command)
    model = run / "model"
    epochs = 2 if args.quick else 6
    command = ["pretrain", "--source", run / "source", "--seed", 0, "--epochs", epochs]
    command += ["--threads", 1, "--no-progress", "--out", model]
    commands.append("dali " + " ".join(map(str, command)))
    if not (model / "manifest.json").is_file():
        dali(*command)
    return model, run / "target", run / "target_val", commands


def save(results: dict, path: Path, fronts: list[str]) -> dict:
    """Write `results` to `path`, merged into what a run of other fronts left there."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.is_file() and set(fronts) != set(FRONTS):
        previous = json.loads(path.read_text())
        previous.update({k: v for k, v in results.items() if k != "command"})
        results = previous
    path.write_text(json.dumps(results, indent=2) + "\n")
    return results


def section(name: str, threads: int, repeats: int, command: str, measure) -> dict:
    print(f"== {name}", file=sys.stderr, flush=True)
    started, load = time.perf_counter(), load_average()
    result = measure()
    return {
        "command": command,
        "machine": machine(threads),
        "repeats": repeats,
        "load_average_before": load,
        "load_average_after": load_average(),
        "wall_seconds": round(time.perf_counter() - started, 1),
        **(result if isinstance(result, dict) else {"points": result}),
    }


def plot(results: dict) -> None:
    from pareto.plots import front_plot

    note = (
        "2-core machine; medians of repeats; machine and load average in bench/results/pareto.json"
    )
    if "raycast" in results:
        points = results["raycast"]["points"]
        for p in points:
            p["us_per_1000_rays"] = 1e9 / p["rays_per_cpu_second"]
        front_plot(
            PLOTS / "raycast.png",
            "Ray casting: PPCG's casts on an exact box at 1-150 m",
            points,
            "us_per_1000_rays",
            "error_mm_p999_all_rays",
            lambda p: f"{'robust' if p['robust'] else 'fast'}, {p['setup']} set-up",
            "CPU microseconds per 1000 rays (1 thread)",
            "hit error, 99.9th percentile of all rays (mm)",
            note,
            logy=True,
        )
    if "ppcg" in results:
        ppcg = results["ppcg"]
        front_plot(
            PLOTS / "ppcg_mesh_detail.png",
            "PPCG: mesh detail (RC casts vs the 67k-triangle car)",
            ppcg["mesh_detail"],
            "rc_cpu_ms_per_frame",
            "surface_error_mm_p95",
            lambda p: f"{p['mean_triangles'] / 1000:.0f}k tri",
            "RC compute, CPU ms per KITTI-like frame",
            "surface error of RC points, 95th percentile (mm)",
            note,
            logy=True,
        )
        for p in ppcg["library_size"]:
            p["rc_cf_cpu_ms_per_frame"] = p["rc_cpu_ms_per_frame"] + p["cf_cpu_ms_per_frame"]
        front_plot(
            PLOTS / "ppcg_library_size.png",
            "PPCG: library size (procedural cars)",
            ppcg["library_size"],
            "rc_cf_cpu_ms_per_frame",
            "size_fit_error_percent",
            lambda p: f"{p['cars']} cars",
            "RC + CF compute, CPU ms per KITTI-like frame",
            "size mismatch of the selected model (mean |model/box - 1|, %)",
            note,
        )
    if "ptsn" in results:
        points = results["ptsn"]["points"]
        for p in points:
            p["scale_error_plot"] = p["scale_error"]
        front_plot(
            PLOTS / "ptsn.png",
            f"PTSN: ŝ vs the full grid on all frames (ŝ_ref = {results['ptsn']['reference_scale']:.3f})",
            points,
            "seconds",
            "scale_error_plot",
            lambda p: (
                f"{p['search']} {p['step']:g}, {p['frames']} fr"
                + (f" (sub {p['subsample_frames']})" if p["subsample_frames"] else "")
            ),
            "seconds (detector frame passes x measured s/pass)",
            "|ŝ - ŝ_ref|",
            note,
            logx=True,
        )
    if "detector" in results:
        points = [p for p in results["detector"]["points"] if "error" not in p]
        for p in points:
            p["ap_loss"] = 100.0 - (p["ap3d_07_all"] or 0.0)
        front_plot(
            PLOTS / "detector.png",
            "Detector inference knobs (one checkpoint)",
            points,
            "seconds_per_frame",
            "ap_loss",
            lambda p: f"{'ref' if p['refine'] else 'no-ref'} {p['precision']} {p['threads']}t",
            "inference seconds per frame",
            "100 - AP_3D@0.7 (all boxes)",
            note,
        )
    if "pillar" in results:
        from pareto.pillar_front import seed_means

        front_plot(
            PLOTS / "pillar.png",
            "Detector pillar size (a model per value, target labels; mean over seeds)",
            seed_means(results["pillar"]["points"]),
            "train_seconds",
            "ap_loss",
            lambda p: f"{p['pillar_m']:.2f} m, {p['frames_seen']} fr ({p['seeds']} seeds)",
            "training seconds (frames/s and inference s/frame: docs/pareto/tables.md)",
            "100 - AP_3D@0.7 (all boxes)",
            note,
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke test: few frames and points")
    parser.add_argument("--only", default=",".join(FRONTS), help="comma-separated fronts to run")
    parser.add_argument(
        "--repeats", type=int, default=None, help="timing repeats (default 5; 1 quick)"
    )
    parser.add_argument(
        "--frames", type=int, default=None, help="PPCG frames (default 12; 3 quick)"
    )
    parser.add_argument(
        "--ptsn-frames", type=int, default=16, help="target frames for PTSN and the detector"
    )
    parser.add_argument(
        "--pillar-seeds", default="0", help="training seeds of the pillar front (comma-separated)"
    )
    parser.add_argument(
        "--pillar-epochs", type=int, default=None, help="pillar front epochs (default 10; 1 quick)"
    )
    parser.add_argument("--model", default=None)
    parser.add_argument("--target", default=None)
    parser.add_argument("--target-val", default=None)
    parser.add_argument("--run", default=str(ROOT / "runs" / "bench_pareto"))
    parser.add_argument(
        "--results", default=None, help="JSON path (default bench/results/pareto.json)"
    )
    args = parser.parse_args()
    only = [f for f in args.only.split(",") if f]
    unknown = sorted(set(only) - set(FRONTS))
    if unknown:
        parser.error(f"unknown front {unknown[0]} (known: {', '.join(FRONTS)})")
    repeats = args.repeats or (1 if args.quick else 5)
    frames_count = args.frames or (3 if args.quick else 12)
    results_path = (
        Path(args.results)
        if args.results
        else (ROOT / "bench" / "results" / "pareto-quick.json" if args.quick else RESULTS)
    )
    base = "python bench/pareto.py" + (" --quick" if args.quick else "")
    results: dict = {
        "command": " ".join(["python bench/pareto.py", *sys.argv[1:]]),
        "quick": args.quick,
    }
    if "raycast" in only:
        from pareto import raycast_front

        results["raycast"] = section(
            "raycast", 1, repeats, f"{base} --only raycast",
            lambda: raycast_front.measure(repeats, boxes=30 if args.quick else 120),
        )  # fmt: skip
    if "ppcg" in only:
        from pareto import ppcg_front
        from pareto.data import jittered_frames

        def ppcg():
            frames = jittered_frames("kitti", frames_count, seed=5)
            cars = 10 if args.quick else 24
            return {
                "frames": frames_count,
                "mesh_detail": ppcg_front.mesh_detail(frames, "kitti", cars, repeats),
                "library_size": ppcg_front.library_size(
                    frames, "kitti", ppcg_front.DEFAULT_LOD, repeats
                ),
                "cf_window": ppcg_front.cf_window(
                    frames[:2], "kitti", ppcg_front.DEFAULT_LOD, cars, repeats
                ),
                "skips": ppcg_front.skips(frames, "kitti", ppcg_front.DEFAULT_LOD, cars, repeats),
            }

        results["ppcg"] = section("ppcg", 1, repeats, f"{base} --only ppcg", ppcg)
    if {"ptsn", "detector", "pillar"} & set(only):
        model, target, target_val, commands = ensure_model(args)
        results["model"] = {"model": str(model), "target": str(target), "target_val": str(target_val),
                            "built_with": commands}  # fmt: skip
        data = f" --model {model} --target {target} --target-val {target_val}"
        data += f" --ptsn-frames {args.ptsn_frames}"
        seeds = [int(seed) for seed in args.pillar_seeds.split(",") if seed]
        epochs = args.pillar_epochs or (1 if args.quick else 10)
        # name -> (measure, threads timed, repeats, the command's extra arguments)
        fronts = {
            "ptsn": (
                lambda: import_module("pareto.ptsn_front").measure(
                    model, target, "kitti", quick=args.quick, frames=args.ptsn_frames
                ),
                0, 1, "",
            ),
            "detector": (
                lambda: import_module("pareto.detector_front").measure(
                    model, target_val, "kitti", quick=args.quick, frames=args.ptsn_frames,
                    repeats=repeats,
                ),
                0, repeats, f" --repeats {repeats}",
            ),
            "pillar": (
                lambda: import_module("pareto.pillar_front").measure(
                    target, target_val, Path(args.run) / "pillar", epochs, seeds,
                    quick=args.quick,
                ),
                2, 1, f" --pillar-seeds {args.pillar_seeds} --pillar-epochs {epochs}",
            ),
        }  # fmt: skip
        for name, (measure, threads, timed, extra) in fronts.items():
            if name in only:
                command = f"{base} --only {name}{data}{extra}"
                results[name] = section(name, threads, timed, command, measure)
                save(results, results_path, only)  # a later front's crash keeps this one
    results = save(results, results_path, only)
    if not args.quick:
        from pareto.tables import markdown

        plot(results)
        (PLOTS / "tables.md").write_text(markdown(results))
    results_path.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {results_path}")


if __name__ == "__main__":
    main()
