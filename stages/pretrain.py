"""Stage: pretrain — train the detector on a labeled source frame set (optionally with SN or ROS)
and write a checkpoint directory (model.pt, model.json, train_log.parquet, manifest.json).

Also holds the pieces retrain shares: resume handling, checkpoint metadata, the training log."""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from dataclasses import asdict
from pathlib import Path

import click
import numpy as np

from dali_cli.manifest import BuildResult, StageOutcome, content_hash, run_stage
from dali_cli.model_card import ModelCard

SIZE_NORMS = ("none", "sn", "ros")


def resume_path_for(out: Path) -> Path:
    """Where an interrupted training run keeps its state: beside the output, stable across runs."""
    return out.parent / f"{out.name}.resume" / "state.pt"


def resume_key(inputs: dict, params: dict) -> str:
    """A run may resume only from a state written with the same inputs and parameters."""
    hashes = {
        name: [content_hash(p) for p in (value if isinstance(value, list | tuple) else [value])]
        for name, value in inputs.items()
        if value is not None
    }
    document = json.dumps({"inputs": hashes, "params": params}, sort_keys=True, default=str)
    return hashlib.blake2b(document.encode(), digest_size=16).hexdigest()


def write_train_log(directory: Path, rows: list[dict]) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    pq.write_table(pa.Table.from_pylist(rows), directory / "train_log.parquet")


def training_summary(result, settings) -> dict:
    tail = result.log[-5:]
    return {
        "steps": result.steps,
        "frames": result.frames,
        "seconds": round(result.seconds, 1),
        "frames_per_s": round(result.frames / max(result.seconds, 1e-9), 2),
        "resumed_from_step": result.resumed_from_step,
        "final_loss": float(np.mean([r["loss"] for r in tail])) if tail else None,
        "settings": asdict(settings),
        "runtime": result.runtime,
    }


def attach_database(data, config, augment: bool) -> None:
    """Give `data` its gt-sampling database (its own boxes inside the detection region), or
    none when augmentation is off."""
    from dali_cli.detector.augment import ObjectDatabase
    from dali_cli.detector.data import detection_region

    data.database = (
        ObjectDatabase.build(data.points, data.boxes, region=detection_region(config))
        if augment
        else None
    )


def fit_and_save(
    tmp: Path,
    net,
    datasets: list,
    augmentations: list,
    settings,
    resume: Path,
    key: str,
    *,
    meta: dict,
    counts: dict,
    notes: list[str],
    load_s: float,
    progress: bool,
    world=None,
) -> BuildResult | None:
    """The training body pretrain, retrain and self-train share: train `net` on `datasets` on
    `world` (its device; the ranks of a torchrun run), write model.pt + model.json (`meta` plus
    the training summary) + train_log.parquet into `tmp`, and return the manifest's counts,
    timings and runtime (threads, device, world size, CPU/GPU model, torch). A rank other than
    0 of a distributed run trains with the others and writes nothing (`tmp` None)."""
    from dali_cli.detector import save_checkpoint, train
    from dali_cli.detector.distributed import SINGLE

    world = world or SINGLE
    result = train(
        net, datasets, augmentations, settings, resume, key, progress=progress,
        device=world.device, world=world,
    )  # fmt: skip
    report_ranks(result, world)
    if tmp is None:
        return None
    save_checkpoint(tmp, net, {**meta, "train": training_summary(result, settings)})
    write_train_log(tmp, result.log)
    if result.resumed_from_step:
        notes = [*notes, f"resumed from step {result.resumed_from_step}"]
    return BuildResult(
        counts={**counts, "steps": result.steps, "frames_seen": result.frames},
        timings={"load_seconds": round(load_s, 2), "train_seconds": round(result.seconds, 2)},
        notes=notes,
        extra={"runtime": result.runtime},
    )


def report_ranks(result, world) -> None:
    """One log line per rank: which engine, and what this rank did."""
    runtime = result.runtime
    engine = (
        f"rank {world.rank} of {world.size} ({world.backend}, DDP)"
        if world.distributed
        else "1 process"
    )
    click.echo(
        f"train: {engine} on {runtime.get('device')}, {runtime.get('threads')} threads: "
        f"{result.steps} steps, {result.frames} frames (all ranks) in {result.seconds:.1f} s",
        err=True,
    )


def run_training_stage(
    stage: str,
    out: Path,
    inputs: dict,
    params: dict,
    train_fn,
    force: bool,
    dry_run: bool,
    seed: int,
    device: str = "auto",
) -> StageOutcome:
    """run_stage around `train_fn(tmp_dir, resume_path, resume_key, world) -> BuildResult`, then
    drop the resume state once the checkpoint is in place.

    `device` (auto | cpu | cuda | cuda:N) is resolved first: a missing GPU fails before anything
    is written. Under torchrun (dali_cli.detector.distributed) rank 0 runs the stage as usual and
    tells the other ranks whether to train; they train with it and write nothing, and rank 0
    commits only after every rank finished (a failing rank fails the stage, no artifact)."""
    from dali_cli.detector import distributed
    from dali_cli.device import resolve_device

    world = distributed.launched()
    torch_device = resolve_device(device, world.local_rank if world.distributed else None)
    if world.distributed:  # the global batch is batch_size x world size: another training
        params = {**params, "world_size": world.size}
    resume = resume_path_for(out)
    key = None
    world = distributed.join(world, torch_device)
    started = False

    def build(tmp: Path) -> BuildResult:
        nonlocal started
        distributed.broadcast_object("train", world)
        started = True
        result = train_fn(tmp, resume, resume_key(inputs, params), world)
        distributed.all_succeeded(world)
        return result

    try:
        if not world.is_main:  # a follower: train when rank 0 does, write nothing
            decision = distributed.broadcast_object(None, world)
            if decision != "train":
                return StageOutcome("follower", f"rank 0: {decision}")
            train_fn(None, resume, key, world)
            distributed.all_succeeded(world)
            return StageOutcome(
                "follower", f"rank {world.rank} of {world.size}; rank 0 wrote {out}"
            )
        outcome = run_stage(
            stage, out, inputs, params, build, force=force, dry_run=dry_run, seed=seed
        )
        if not started:
            distributed.broadcast_object(outcome.status, world)
    finally:
        distributed.leave()
    if outcome.status == "ran":
        shutil.rmtree(resume.parent, ignore_errors=True)
    return outcome


def run_pretrain(
    source: str | Path,
    out: str | Path,
    *,
    boxes: str | Path | None = None,
    size_norm: str = "none",
    target_profile: str | None = None,
    target_size: tuple[float, float, float] | None = None,
    ros_range: tuple[float, float] = (0.75, 1.0),
    epochs: float = 10.0,
    minutes: float | None = None,
    seed: int = 0,
    batch_size: int = 1,
    lr: float = 5e-3,
    features: str = "xyz",
    precision: str = "fp32",
    compile_net: bool = False,
    threads: int | None = None,
    augment: bool = True,
    labels: tuple[str, ...] = ("Car",),
    config_overrides: dict | None = None,
    sensors_path: str | Path | None = None,
    force: bool = False,
    dry_run: bool = False,
    progress: bool = True,
    device: str = "auto",
) -> StageOutcome:
    """Train on `source` (FrameSet + boxes.parquet) and write the checkpoint to `out` (on
    `device`; under torchrun with DDP, see run_training_stage)."""
    from dali_cli.sensors import get_profile

    source, out = Path(source), Path(out)
    if size_norm not in SIZE_NORMS:
        raise click.UsageError(
            f"--size-norm must be one of {', '.join(SIZE_NORMS)}, got '{size_norm}'"
        )
    if size_norm == "sn" and target_profile is None and target_size is None:
        raise click.UsageError("--size-norm sn needs --target-profile (or --target-size)")
    if target_size is None and target_profile is not None and size_norm == "sn":
        target_size = tuple(get_profile(target_profile, sensors_path).car_mean_lwh_m)
    if config_overrides:
        from dali_cli.detector.config import DetectorConfig

        try:
            DetectorConfig.from_dict(config_overrides)
        except (TypeError, ValueError) as error:
            raise click.UsageError(f"detector config: {error}") from None
    params = {
        "size_norm": size_norm,
        "target_profile": target_profile,
        "target_size": list(target_size) if size_norm == "sn" else None,
        "ros_range": list(ros_range) if size_norm == "ros" else None,
        "epochs": None if minutes else epochs,
        "minutes": minutes,
        "seed": seed,
        "batch_size": batch_size,
        "lr": lr,
        "features": features,
        "precision": precision,
        "compile": compile_net,
        "augment": augment,
        "labels": list(labels),
        "config": config_overrides or {},
    }
    inputs = {"source": source, "boxes": Path(boxes) if boxes else None}

    def train_fn(tmp: Path | None, resume: Path, key: str, world) -> BuildResult | None:
        import torch

        from dali_cli.detector import (
            Augmentation,
            DetectorConfig,
            PillarCenterNet,
            TrainSettings,
            load_labeled,
            size_normalize,
        )

        started = time.perf_counter()
        config = DetectorConfig.from_dict({**(config_overrides or {}), "features": features})
        data = load_labeled(
            source, config, boxes_dir=boxes, labels=labels, sensors_path=sensors_path
        )
        config.sensor, config.mount_height_m = data.sensor, data.mount_height_m
        if data.num_boxes == 0:
            raise click.ClickException(
                f"{boxes or source}: no '{'/'.join(labels)}' boxes with points to train on"
            )
        source_mean = data.mean_lwh()
        delta = None
        if size_norm == "sn":
            delta = np.asarray(target_size) - source_mean
            data = size_normalize(data, delta)
        attach_database(data, config, augment)
        augmentation = Augmentation() if augment else Augmentation.none()
        if size_norm == "ros":
            augmentation.object_scale = tuple(ros_range)
        load_s = time.perf_counter() - started
        torch.manual_seed(seed)
        net = PillarCenterNet(config)
        settings = TrainSettings(
            epochs=epochs, minutes=minutes, batch_size=batch_size, lr=lr, seed=seed,
            precision=precision, compile=compile_net, threads=threads, device=device,
        )  # fmt: skip
        card = ModelCard(
            detector=config.name,
            stage="pretrain",
            source_sensor=data.sensor,
            mount_height_m=data.mount_height_m,
            source_mean_lwh_m=tuple(float(v) for v in source_mean),
            size_norm=size_norm,
            sn_delta_lwh_m=None if delta is None else tuple(float(v) for v in delta),
            ros_range=tuple(ros_range) if size_norm == "ros" else None,
            target_profile=target_profile,
        )
        meta = {
            "card": card.to_dict(),
            "provenance": {
                "stage": "pretrain",
                "source": str(source),
                "source_hash": content_hash(source),
                "source_sensor": data.sensor,
                "size_norm": size_norm,
                "target_profile": target_profile,
                "sn_delta_lwh": None if delta is None else delta.tolist(),
                "ros_range": list(ros_range) if size_norm == "ros" else None,
                "seed": seed,
            },
            "metrics": {
                "source_mean_lwh_m": source_mean.tolist(),
                "trained_mean_lwh_m": data.mean_lwh().tolist(),
                "frames": len(data),
                "boxes": data.num_boxes,
                "database_instances": 0 if data.database is None else len(data.database),
            },
        }
        return fit_and_save(
            tmp, net, [data], [augmentation], settings, resume, key,
            meta=meta,
            counts={"frames": len(data), "boxes": data.num_boxes},
            notes=[f"detector: {net.config.name} (not the paper's SECOND-IoU), size_norm={size_norm}"],
            load_s=load_s,
            progress=progress,
            world=world,
        )  # fmt: skip

    return run_training_stage(
        "pretrain", out, inputs, params, train_fn, force, dry_run, seed, device
    )
