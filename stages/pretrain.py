"""Stage: pretrain — train the detector on a labeled source frame set (optionally with SN or ROS)
and write a checkpoint directory (model.pt, model.json, train_log.parquet, manifest.json).
The training body it shares with retrain and self-train is dali_cli.training_stage."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from dali_cli.errors import ParameterError, StageError
from dali_cli.manifest import BuildResult, StageOutcome, content_hash
from dali_cli.model_card import ModelCard
from dali_cli.training_stage import attach_database, fit_and_save, run_training_stage

SIZE_NORMS = ("none", "sn", "ros")


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
        raise ParameterError(
            "size_norm", f"must be one of {', '.join(SIZE_NORMS)}, got '{size_norm}'"
        )
    if size_norm == "sn" and target_profile is None and target_size is None:
        raise ParameterError(
            ("target_profile", "target_size"), "size normalization sn needs the target's car size"
        )
    if target_size is None and target_profile is not None and size_norm == "sn":
        target_size = tuple(get_profile(target_profile, sensors_path).car_mean_lwh_m)
    if config_overrides:
        from dali_cli.detector.config import DetectorConfig

        try:
            DetectorConfig.from_dict(config_overrides)
        except (TypeError, ValueError) as error:
            raise ParameterError("config_overrides", f"detector config: {error}") from None
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
            raise StageError(
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
