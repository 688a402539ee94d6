"""Synthetic labelled LiDAR frames: street scenes of procedural cars and clutter, scanned by a sensor
profile (the world: dali_cli.world — car pool, scene layout, scanning), written as a FrameSet with
boxes.

Everything random comes from (seed, frame index), so frame k is the same whatever the number of
frames, their order or the worker count.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dali_cli.sensors import SensorProfile
from dali_cli.world.cars import pool_car
from dali_cli.world.scan import scan_scene
from dali_cli.world.scene import generate_scene

FRAME_SALT = 0x53594E54


# ---------------------------------------------------------------------------------------------
# Frames


def frame_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of frame `index` of a run with `seed` (independent of everything else)."""
    return np.random.default_rng(
        np.random.SeedSequence([FRAME_SALT, int(seed) & 0xFFFFFFFF, int(index)])
    )


def frame_id(index: int) -> str:
    return f"{int(index):06d}"


@dataclass
class SynthFrame:
    """One frame: points `(n, 4)` float32 and labels of the cars with >= 1 point.

    boxes `(K, 7)`, num_points `(K,)` int32, occlusion `(K,)` float32 (share of the car's
    unoccluded rays that something else blocked), kind `(K,)` str, model `(K,)` int32 pool index.
    owner `(n,)` int32: label row of each point (-1 ground, -2 clutter).
    """

    frame_id: str
    points: np.ndarray
    boxes: np.ndarray
    num_points: np.ndarray
    occlusion: np.ndarray
    kind: np.ndarray
    model: np.ndarray
    owner: np.ndarray


def synth_frame(
    seed: int, index: int, sensor: SensorProfile, cars: SensorProfile, threads: int = 1
) -> SynthFrame:
    """Generate and scan frame `index` of a run with `seed` (deterministic per (seed, index))."""
    rng = frame_rng(seed, index)
    scene = generate_scene(rng, sensor, cars)
    scan = scan_scene(scene, sensor, rng, threads=threads)
    counts = np.bincount(scan.owner[scan.owner >= 0], minlength=len(scene.cars))
    labeled = np.flatnonzero(counts >= 1)
    row_of_car = np.full(
        len(scene.cars) + 3, -1, np.int64
    )  # indices -3..-1 map to themselves below
    row_of_car[labeled] = np.arange(len(labeled))
    owner = np.where(scan.owner >= 0, row_of_car[np.maximum(scan.owner, 0)], scan.owner).astype(
        np.int32
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        occlusion = 1.0 - scan.car_visible_rays / scan.car_unoccluded_rays
    occlusion = np.clip(np.nan_to_num(occlusion, nan=1.0), 0.0, 1.0)
    models = scene.car_models[labeled]
    return SynthFrame(
        frame_id=frame_id(index),
        points=scan.points,
        boxes=scene.cars[labeled],
        num_points=counts[labeled].astype(np.int32),
        occlusion=occlusion[labeled].astype(np.float32),
        kind=np.array([pool_car(int(m)).kind for m in models], dtype=object),
        model=models.astype(np.int32),
        owner=owner,
    )


# ---------------------------------------------------------------------------------------------
# The stage


def iter_frames(
    seed: int, frames: range | int, sensor: SensorProfile, cars: SensorProfile, threads: int = 1
):
    """Yield SynthFrames of `frames` (a range of indices, or 0..frames-1) in order, each traced
    with `threads` Embree threads, in this process (the serial path; see SynthShards)."""
    indices = range(int(frames)) if isinstance(frames, int) else frames
    for index in indices:
        yield synth_frame(int(seed), index, sensor, cars, threads=int(threads))


def frame_table(frame: SynthFrame):
    """One frame's labels as a BoxTable: every car with >= 1 point, its KITTI label fields."""
    from dali_cli.importers.camera import kitti_label_columns
    from dali_cli.store.artifacts import BoxTable

    return BoxTable.from_arrays(
        np.full(len(frame.boxes), frame.frame_id, dtype=object),
        frame.boxes,
        label="Car",
        num_points=frame.num_points,
        occlusion=frame.occlusion,
        kind=frame.kind.astype(str),
        car_model=frame.model,
        # after the scan, from the boxes alone: no random draw, points unchanged
        **kitti_label_columns(frame.boxes, frame.occlusion),
    )


@dataclass(frozen=True)
class SynthShards:
    """Worker factory and worker of the sharded path (dali_cli.executors): a shard's frames
    and labels, written as shard files (points) and boxes.parquet. Nothing to load."""

    seed: int
    sensor: SensorProfile
    cars: SensorProfile
    threads: int = 1

    def __call__(self) -> SynthShards:
        return self

    def run(self, shard, directory: Path) -> dict:
        from dali_cli.executors import naming_frames
        from dali_cli.executors.shards import ShardFramesWriter
        from dali_cli.store.artifacts import BoxTable, write_boxes

        writer, tables = ShardFramesWriter(directory), []
        for index in range(shard.start, shard.stop):
            with naming_frames(frame_id(index)):
                frame = synth_frame(self.seed, index, self.sensor, self.cars, self.threads)
            writer.append(frame.frame_id, frame.points)
            tables.append(frame_table(frame))
        points = writer.close()
        write_boxes(directory, BoxTable.concat(tables))
        return {"points": points}


def synth_counts(table, frames: int, total_points: int) -> dict:
    """The manifest's counts of a synthetic set: frames, points, labels (per frame, mean l, w,
    h in m) and the mean points per car by range band (0-30, 30-50, 50-80 m)."""
    lwh = table.boxes[:, 3:6] if len(table) else np.zeros((0, 3))
    distance = np.hypot(table["x"], table["y"]) if len(table) else np.zeros(0)
    bands = {}
    for low, high in ((0, 30), (30, 50), (50, 80)):
        inside = (distance >= low) & (distance < high)
        bands[f"{low}-{high}m"] = (
            float(np.mean(table["num_points"][inside])) if inside.any() else 0.0
        )
    return {
        "frames": int(frames),
        "points": int(total_points),
        "labels": len(table),
        "labels_per_frame": round(len(table) / max(frames, 1), 2),
        "mean_label_lwh_m": [round(float(v), 3) for v in lwh.mean(axis=0)] if len(lwh) else None,
        "mean_points_per_car_by_range": {k: round(v, 1) for k, v in bands.items()},
    }


def build_synth(
    out_dir,
    sensor: SensorProfile,
    cars: SensorProfile,
    frames: int,
    seed: int,
    progress: bool = True,
    threads: int = 1,
    executor=None,
):
    """Write `frames` synthetic frames as a FrameSet + boxes.parquet into `out_dir`, in this
    process or, given a parallel `executor` (dali_cli.executors), as shards on its workers
    merged in order (the same bytes).

    Returns a manifest.BuildResult with counts (frames, points, labels, mean label size, points
    per car by range band) and timings.
    """
    import time

    from tqdm import tqdm

    from dali_cli.store.artifacts import BoxTable, FrameSetWriter, read_boxes, write_boxes
    from dali_cli.store.manifest import BuildResult

    started = time.perf_counter()
    attrs = {
        "synthetic": True,
        "cars_profile": cars.name,
        "seed": int(seed),
        "mount_height_m": sensor.mount_height_m,
    }
    tables, total_points = [], 0
    bar = tqdm(total=frames, desc=f"synth {sensor.name}", unit="frame", disable=not progress)
    with FrameSetWriter(out_dir, sensor.name, attrs) as writer:
        if executor is None or executor.serial:
            for frame in iter_frames(seed, frames, sensor, cars, threads):
                writer.append(frame.frame_id, frame.points)
                total_points += len(frame.points)
                tables.append(frame_table(frame))
                bar.update(1)
        else:
            from dali_cli.executors import plan_shards, shard_results
            from dali_cli.executors.shards import read_shard_frames

            ids = [frame_id(index) for index in range(frames)]
            worker = SynthShards(int(seed), sensor, cars, int(threads))
            shards = plan_shards(ids, executor.workers, max_frames=16)
            for shard, directory, _ in shard_results(executor, worker, shards, Path(out_dir)):
                for name, points in read_shard_frames(directory):
                    writer.append(name, points)
                    total_points += len(points)
                tables.append(read_boxes(directory))
                bar.update(len(shard.frame_ids))
    bar.close()
    table = BoxTable.concat(tables)
    write_boxes(out_dir, table)
    elapsed = time.perf_counter() - started
    counts = synth_counts(table, frames, total_points)
    timings = {"frames_per_second": round(frames / max(elapsed, 1e-9), 2)}
    notes = [
        "synthetic street scenes: procedural cars (pool seeds disjoint from `dali library build`), "
        "walls, sidewalks, fences, hedges, poles, trees, bushes, containers; first-hit scan with "
        "range noise, dropout, weak far echoes lost and max range; labels for every car with >= 1 "
        "point",
        "occlusion = share of a car's rays blocked by something nearer (0 = fully visible)",
        "KITTI label fields (truncated, occluded level, alpha, bbox_*) from a virtual KITTI left "
        "colour camera at the sensor (dali_cli.importers.camera), so `dali eval --protocol kitti` gives "
        "easy/moderate/hard",
    ]
    extra = {"executor": executor.report()} if executor is not None else {}
    return BuildResult(counts=counts, timings=timings, notes=notes, extra=extra)
