"""Benchmark: frames/s of the per-frame stages (synth, ppcg-rc, ppcg-cf, pseudo-label) with 1 and
2 workers on the local engine (1 = in this process, the serial reference; 2 = the process pool)
and on Ray (actors on a local Ray instance, started once as a cluster would be), plus Ray's
start-up and per-task overhead. The goal: 2 workers >= 1.6 x one worker.

Every run is a whole stage (`--force`), so frames/s include reading, the shard round trip
(workers write shards, the driver merges them) and writing; each run records the 1-minute load
average before and after it (the machine may be shared: compare runs of similar load). The
detector is --model, or the default configuration with random weights (the trained model's
network, but not its boxes: many low-score boxes to refine); PPCG processes the target's own
labels.

Writes bench/results/scale.json.
    .venv/bin/python bench/scale.py [--frames 48] [--ppcg-frames 192] [--repeats 1]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results" / "scale.json"
ENGINES = (("local", 1), ("local", 2), ("ray", 1), ("ray", 2))


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def load() -> float:
    return round(os.getloadavg()[0], 2)


def prepare(root: Path, frames: int, ppcg_frames: int, sensor: str) -> dict:
    """Target frame sets (synth of `sensor`, serial) and a default-size detector."""
    import torch

    from dali_cli.detector.config import DetectorConfig
    from dali_cli.detector.infer import save_checkpoint
    from dali_cli.detector.model import PillarCenterNet
    from dali_cli.sensors import get_profile
    from dali_cli.synth import build_synth

    profile = get_profile(sensor)
    paths = {"target": root / "target", "ppcg_target": root / "ppcg_target"}
    for name, count in (("target", frames), ("ppcg_target", ppcg_frames)):
        paths[name].mkdir()
        build_synth(paths[name], profile, profile, count, 11, progress=False)
    torch.manual_seed(0)
    paths["model"] = root / "model"
    paths["model"].mkdir()
    save_checkpoint(paths["model"], PillarCenterNet(DetectorConfig()), {"provenance": {}})
    return paths


def build_library(root: Path) -> Path:
    from click.testing import CliRunner

    from dali_cli.cli import main

    out = root / "library"
    result = CliRunner().invoke(
        main, ["library", "build", "--procedural", "24", "--seed", "4000", "--out", str(out)]
    )
    if result.exit_code:
        raise RuntimeError(result.output)
    return out


def run_stage(
    stage: str,
    paths: dict,
    out: Path,
    engine: str,
    workers: int,
    frames: int,
    address: str | None,
    sensor: str,
) -> tuple[float, float, dict]:
    """Run one stage as a user would (`dali ...` in a fresh process, --force); returns the
    command's wall and CPU seconds (its workers' included) and its manifest (wall_seconds = the
    stage's own build time)."""
    from dali_cli.store.manifest import read_manifest

    dali = str(Path(sys.executable).with_name("dali"))
    engine_args = ["--executor", engine, "--workers", str(workers)]
    if engine == "ray":
        engine_args += ["--ray-address", address]
    if stage == "synth":
        command = [dali, "synth", "--sensor", sensor, "--frames", str(frames), "--seed", "11"]
    elif stage == "pseudo-label":
        command = [dali, "pseudo-label", "--model", str(paths["model"]), "--data",
                   str(paths["target"]), "--scale", "1.0", "--no-progress"]  # fmt: skip
    else:
        command = [dali, stage, "--data", str(paths["ppcg_target"]), "--boxes",
                   str(paths["ppcg_target"]), "--library", str(paths["library"]), "--no-progress"]  # fmt: skip
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    done = subprocess.run(
        [*command, *engine_args, "--force", "--out", str(out)], capture_output=True, text=True
    )
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode:
        raise RuntimeError(f"{' '.join(command)} failed:\n{done.stdout}\n{done.stderr}")
    # CPU of the command and of the pool processes it reaped (Ray actors are the Ray node's
    # children: their CPU comes from the manifest's per-worker record)
    cpu = (after.ru_utime + after.ru_stime) - (usage.ru_utime + usage.ru_stime)
    manifest = read_manifest(out)
    if engine == "ray":
        per_worker = (manifest.get("executor") or {}).get("per_worker", {})
        cpu += sum(w.get("cpu_seconds", 0.0) for w in per_worker.values())
    return wall, cpu, manifest


def start_ray_head(port: int) -> tuple[subprocess.Popen, float]:
    """`ray start --head --block` as our own child (stopped by its pid at the end, never with
    `ray stop`, which would stop every Ray of the machine); returns it and its start-up time."""
    import ray

    ray_cli = str(Path(sys.executable).with_name("ray"))
    started = time.perf_counter()
    head = subprocess.Popen(
        [ray_cli, "start", "--head", "--block", f"--port={port}", "--num-cpus=2",
         "--include-dashboard=false", "--object-store-memory=134217728", "--disable-usage-stats"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )  # fmt: skip
    deadline = time.monotonic() + 120
    while True:
        try:
            ray.init(address=f"127.0.0.1:{port}", logging_level="WARNING", log_to_driver=False)
            break
        except Exception:
            if time.monotonic() > deadline or head.poll() is not None:
                head.kill()
                raise
            time.sleep(0.5)
    return head, time.perf_counter() - started


def stop_ray_head(head: subprocess.Popen, port: int) -> None:
    """End the head and the processes it started (its own session: one process group)."""
    os.killpg(head.pid, signal.SIGTERM)
    try:
        head.wait(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(head.pid, signal.SIGKILL)
    # the head's record of "the cluster on this node" (what `ray stop` would remove), if ours
    record = Path(tempfile.gettempdir()) / "ray" / "ray_current_cluster"
    if record.is_file() and record.read_text().strip().endswith(f":{port}"):
        record.unlink()


def ray_overheads(ray, calls: int = 200) -> dict:
    """Start-up of actors and round trips of no-op calls (one actor) and of no-op tasks."""

    @ray.remote(num_cpus=1)
    class Echo:
        def ping(self, value):
            return value

    @ray.remote(num_cpus=1)
    def ping(value):
        return value

    started = time.perf_counter()
    actor = Echo.remote()
    ray.get(actor.ping.remote(0))
    actor_start = time.perf_counter() - started
    started = time.perf_counter()
    for index in range(calls):
        ray.get(actor.ping.remote(index))
    actor_call = (time.perf_counter() - started) / calls
    ray.get(ping.remote(0))  # warm a worker
    started = time.perf_counter()
    for index in range(calls):
        ray.get(ping.remote(index))
    task_call = (time.perf_counter() - started) / calls
    ray.kill(actor)
    return {
        "actor_start_seconds": round(actor_start, 3),
        "actor_call_round_trip_ms": round(actor_call * 1e3, 3),
        "task_round_trip_ms": round(task_call * 1e3, 3),
    }


def driver_merge(frames_dir: Path, root: Path) -> dict:
    """The driver's serial share of a sharded stage: reading shard files and appending their
    frames to the artifact's FrameSetWriter, per frame and per million points, with zstd chunks
    (synth's frames.zarr) and raw chunks (ppcg's)."""
    from dali_cli.executors.shards import ShardFramesWriter, read_shard_frames
    from dali_cli.store.artifacts import FrameSet, FrameSetWriter

    frames = FrameSet(frames_dir)
    shards = []
    writer = None
    for index, (frame_id, points) in enumerate(frames.iter_frames()):
        if index % 16 == 0:
            if writer is not None:
                writer.close()
            shards.append(root / f"merge-shard-{index}")
            shards[-1].mkdir()
            writer = ShardFramesWriter(shards[-1])
        writer.append(frame_id, points)
    writer.close()
    result = {"frames": len(frames), "points_per_frame": round(frames.num_points / len(frames))}
    for compress in (True, False):
        out = root / f"merge-{compress}"
        out.mkdir()
        started, started_cpu = time.perf_counter(), time.process_time()
        with FrameSetWriter(out, frames.sensor, compress=compress) as merged:
            for shard in shards:
                for frame_id, points in read_shard_frames(shard):
                    merged.append(frame_id, points)
        seconds = time.perf_counter() - started
        cpu = time.process_time() - started_cpu
        key = "zstd" if compress else "raw"
        result[f"{key}_ms_per_frame"] = round(seconds / len(frames) * 1e3, 3)
        result[f"{key}_cpu_ms_per_frame"] = round(cpu / len(frames) * 1e3, 3)
        result[f"{key}_seconds_per_million_points"] = round(seconds / frames.num_points * 1e6, 4)
    return result


def pool_overhead(calls: int = 200) -> dict:
    from dali_cli.runtime.workers import process_pool

    started = time.perf_counter()
    with process_pool(1) as pool:
        pool.submit(abs, 0).result()
        start = time.perf_counter() - started
        started = time.perf_counter()
        for index in range(calls):
            pool.submit(abs, index).result()
        call = (time.perf_counter() - started) / calls
    return {"process_start_seconds": round(start, 3), "task_round_trip_ms": round(call * 1e3, 3)}


def measure(args, result: dict, paths: dict, root: Path, address: str) -> None:
    for stage in args.stages.split(","):
        frames = result["frames"][stage]
        rows = {}
        for engine, workers in ENGINES:
            best = None
            for repeat in range(args.repeats):
                before = load()
                out = root / "out" / f"{stage}-{engine}-{workers}-{repeat}"
                wall, cpu, manifest = run_stage(
                    stage, paths, out, engine, workers, frames, address, args.sensor
                )
                report = manifest.get("executor") or {}
                stage_wall = manifest["timings"]["wall_seconds"]
                row = {
                    "command_seconds": round(wall, 3),
                    "stage_seconds": stage_wall,
                    "frames_per_second": round(frames / stage_wall, 3),
                    "command_cpu_seconds": round(cpu, 3),
                    "cpu_seconds_per_frame": round(cpu / frames, 4),
                    "load_before": before,
                    "load_after": load(),
                    "engine_startup_seconds": report.get("startup_seconds"),
                    "per_worker": report.get("per_worker"),
                }
                if best is None or row["stage_seconds"] < best["stage_seconds"]:
                    best = row
                print(
                    f"{stage:13} {engine:5} x{workers}: {row['frames_per_second']:7.2f} frames/s "
                    f"(stage {stage_wall:.1f} s, command {wall:.1f} s, load {before} -> "
                    f"{row['load_after']})",
                    flush=True,
                )
            rows[f"{engine}_{workers}"] = best
        for engine in ("local", "ray"):
            one, two = rows[f"{engine}_1"], rows[f"{engine}_2"]
            rows[f"{engine}_speedup_2_vs_1"] = round(
                two["frames_per_second"] / one["frames_per_second"], 3
            )
        for engine in ("local", "ray"):  # extra CPU the second worker costs (start-up, shards)
            rows[f"{engine}_cpu_2_vs_1"] = round(
                rows[f"{engine}_2"]["command_cpu_seconds"]
                / rows[f"{engine}_1"]["command_cpu_seconds"],
                3,
            )
        rows["ray_2_vs_serial"] = round(
            rows["ray_2"]["frames_per_second"] / rows["local_1"]["frames_per_second"], 3
        )
        result["stages"][stage] = rows


WAYMO_TRAIN_FRAMES = 158_081


def wall_time_model(result: dict, frames: int = WAYMO_TRAIN_FRAMES, workers=(1, 8, 64)) -> dict:
    """Wall time per stage for `frames` frames at each worker count, from the measurements:

        T(W) = s0 + frames * max(t1 / W, td)

    t1 = one worker's seconds per frame (Ray x1 run: read + compute + shard write), s0 = the rest
    of that run's wall time (Ray connect, actor start, model load, driver work that does not
    overlap the workers), td = the driver's merge seconds per frame (zstd chunks for synth, raw
    for PPCG; pseudo-label merges boxes only: 0). Two variants: "measured" uses wall seconds as
    measured on this shared machine (contention inflates t1 and td alike); "dedicated_cores"
    uses CPU seconds (t1: the worker's CPU per frame, all its threads; td: the merge's CPU), what
    a worker with a core of its own would take. Both assume no straggler and a filesystem that
    keeps up."""
    merge = result["driver_merge"]
    model = {"frames": frames, "formula": "T(W) = s0 + frames * max(t1 / W, td)", "stages": {}}
    for stage, rows in result["stages"].items():
        one = rows["ray_1"]
        count = result["frames"][stage]
        busy = sum(w["busy_seconds"] for w in one["per_worker"].values())
        cpu = sum(w.get("cpu_seconds", float("nan")) for w in one["per_worker"].values())
        s0 = max(0.0, one["stage_seconds"] - busy)
        key = {"synth": "zstd", "ppcg-rc": "raw", "ppcg-cf": "raw"}.get(stage)
        variants = {
            "measured": (busy / count, merge[f"{key}_ms_per_frame"] / 1e3 if key else 0.0),
            "dedicated_cores": (
                cpu / count,
                merge.get(f"{key}_cpu_ms_per_frame", float("nan")) / 1e3 if key else 0.0,
            ),
        }
        entry = {"s0_seconds": round(s0, 2)}
        for name, (t1, td) in variants.items():
            if t1 != t1 or td != td:  # NaN: not measured (an older scale.json)
                continue
            entry[name] = {
                "t1_seconds_per_frame": round(t1, 4),
                "td_seconds_per_frame": round(td, 5),
                "hours": {
                    str(w): round((s0 + frames * max(t1 / w, td)) / 3600, 2) for w in workers
                },
                "driver_bound_above_workers": round(t1 / td, 1) if td else None,
            }
        model["stages"][stage] = entry
    return model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=48, help="frames for synth, pseudo-label")
    parser.add_argument("--ppcg-frames", type=int, default=192, help="frames for ppcg-rc/cf")
    parser.add_argument("--repeats", type=int, default=1, help="runs per configuration (best)")
    parser.add_argument("--stages", default="synth,ppcg-rc,ppcg-cf,pseudo-label")
    parser.add_argument(
        "--model", type=Path, default=None,
        help="trained checkpoint for pseudo-label (default: the default detector, random weights)",
    )  # fmt: skip
    parser.add_argument("--sensor", default="kitti", help="sensor profile of the frames")
    parser.add_argument("--port", type=int, default=6390, help="port of the Ray head started")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument(
        "--model-only", action="store_true", help="only recompute the wall-time model of --out"
    )
    parser.add_argument(
        "--merge-only",
        action="store_true",
        help="only remeasure the driver merge (on --ppcg-frames frames) into --out, and the model",
    )
    args = parser.parse_args()
    if args.model_only or args.merge_only:
        result = json.loads(args.out.read_text())
        if args.merge_only:
            with tempfile.TemporaryDirectory(prefix="dali-scale-") as tmp:
                paths = prepare(Path(tmp), 1, args.ppcg_frames, args.sensor)
                result["driver_merge"] = {
                    **driver_merge(paths["ppcg_target"], Path(tmp)),
                    "load_average_1m": load(),
                    "command": f"bench/scale.py --merge-only --ppcg-frames {args.ppcg_frames} "
                    f"--sensor {args.sensor}",
                }
        result["model_waymo_train"] = wall_time_model(result)
        args.out.write_text(json.dumps(result, indent=2) + "\n")
        print(json.dumps(result["model_waymo_train"], indent=2))
        return

    import ray

    result = {
        "machine": {
            "cpu": cpu_model(),
            "cores_available": len(os.sched_getaffinity(0)),
            "load_average_1m_start": load(),
            "shared": "yes: other sessions' experiments and builds ran on the same cores",
        },
        "command": "bench/scale.py "
        + " ".join(
            f"--{k.replace('_', '-')} {v}"
            for k, v in vars(args).items()
            if k != "out" and v is not None and v is not False
        ),
        "frames": {
            "synth": args.frames,
            "pseudo-label": args.frames,
            "ppcg-rc": args.ppcg_frames,
            "ppcg-cf": args.ppcg_frames,
        },  # fmt: skip
        "stages": {},
    }
    with tempfile.TemporaryDirectory(prefix="dali-scale-") as tmp:
        root = Path(tmp)
        paths = prepare(root, args.frames, args.ppcg_frames, args.sensor)
        if args.model is not None:
            paths["model"] = args.model
        paths["library"] = build_library(root)
        result["local_pool_overhead"] = pool_overhead()
        result["driver_merge"] = driver_merge(paths["ppcg_target"], root)
        started = time.perf_counter()  # what `--executor ray` without --ray-address starts
        ray.init(address="local", num_cpus=2, include_dashboard=False, object_store_memory=128 * 2**20,
                 log_to_driver=False, logging_level="WARNING")  # fmt: skip
        local_init = time.perf_counter() - started
        started = time.perf_counter()
        ray.shutdown()
        local_shutdown = time.perf_counter() - started
        head, head_seconds = start_ray_head(args.port)
        address = f"127.0.0.1:{args.port}"
        try:
            started = time.perf_counter()
            ray.shutdown()
            ray.init(address=address, logging_level="WARNING", log_to_driver=False)
            connect = time.perf_counter() - started
            result["ray"] = {
                "version": ray.__version__,
                "local_instance_init_seconds": round(local_init, 3),
                "local_instance_shutdown_seconds": round(local_shutdown, 3),
                "head_start_seconds": round(head_seconds, 3),
                "driver_connect_seconds": round(connect, 3),
                **ray_overheads(ray),
            }
            ray.shutdown()
            measure(args, result, paths, root, address)
        finally:
            stop_ray_head(head, args.port)
    result["machine"]["load_average_1m_end"] = load()
    result["model_waymo_train"] = wall_time_model(result)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
