"""Stage: pretrain — train the detector on a labelled source frame set (optionally with SN or ROS)
and write a checkpoint directory (model.pt, model.json, train_log.parquet, manifest.json).
The training body it shares with retrain and self-train is dali_cli.detector.training_stage."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dali_cli.detector.training_stage import (
    PreparedTraining,
    TrainingOptions,
    attach_database,
    run_training_stage,
    seeded_network,
    target_car_size,
)
from dali_cli.runtime.errors import ParameterError, StageError
from dali_cli.store.manifest import StageOutcome, content_hash
from dali_cli.store.model_card import ModelCard

SIZE_NORMS = ("none", "sn", "ros")


def run_pretrain(
    source: str | Path,
    out: str | Path,
    *,
    training: TrainingOptions = TrainingOptions(),
    boxes: str | Path | None = None,
    size_norm: str = "none",
    target_profile: str | None = None,
    target_size: tuple[float, float, float] | None = None,
    ros_range: tuple[float, float] = (0.75, 1.0),
    features: str = "xyz",
    labels: tuple[str, ...] = ("Car",),
    config_overrides: dict | None = None,
    sensors_path: str | Path | None = None,
    force: bool = False,
    dry_run: bool = False,
) -> StageOutcome:
    """Train on `source` (FrameSet + boxes.parquet) with `training` (budget, optimizer,
    device) and write the checkpoint to `out` (under torchrun with DDP, see
    run_training_stage)."""
    source, out = Path(source), Path(out)
    if size_norm not in SIZE_NORMS:
        raise ParameterError(
            "size_norm", f"must be one of {', '.join(SIZE_NORMS)}, got '{size_norm}'"
        )
    if size_norm == "sn":
        target_size = target_car_size(
            target_profile, target_size, sensors_path, "size normalization sn"
        )
    check_config_overrides(config_overrides)
    params = {
        "size_norm": size_norm,
        "target_profile": target_profile,
        "target_size": list(target_size) if size_norm == "sn" else None,
        "ros_range": list(ros_range) if size_norm == "ros" else None,
        "features": features,
        "labels": list(labels),
        "config": config_overrides or {},
    }
    inputs = {"source": source, "boxes": Path(boxes) if boxes else None}

    def prepare() -> PreparedTraining:
        from dali_cli.detector import DetectorConfig, load_labeled, size_normalize
        from dali_cli.detector.scans_for import for_scans_of

        config = DetectorConfig.from_dict({**(config_overrides or {}), "features": features})
        data = load_labeled(
            source, config, boxes_dir=boxes, labels=labels, sensors_path=sensors_path,
            stream=True,
        )  # fmt: skip
        config = for_scans_of(config, source, sensors_path)
        if data.num_boxes == 0:
            raise StageError(
                f"{boxes or source}: no '{'/'.join(labels)}' boxes with points to train on"
            )
        source_mean = data.mean_lwh()
        delta = None
        if size_norm == "sn":
            delta = np.asarray(target_size) - source_mean
            data = size_normalize(data, delta)
        attach_database(data, config, training.augment)
        augmentation = training.augmentation()
        if size_norm == "ros":
            augmentation.object_scale = tuple(ros_range)
        net = seeded_network(config, training.seed)
        meta = pretrain_meta(
            config, data, source, source_mean, delta, size_norm, ros_range, target_profile,
            training.seed,
        )  # fmt: skip
        return PreparedTraining(
            net, [data], [augmentation], training.settings(),
            meta=meta,
            counts={"frames": len(data), "boxes": data.num_boxes},
            notes=[f"detector: {net.config.name} (not the paper's SECOND-IoU), size_norm={size_norm}"],
        )  # fmt: skip

    return run_training_stage("pretrain", out, inputs, params, prepare, force, dry_run, training)


def pretrain_meta(
    config, data, source: Path, source_mean: np.ndarray, delta: np.ndarray | None,
    size_norm: str, ros_range: tuple[float, float], target_profile: str | None, seed: int,
) -> dict:  # fmt: skip
    """model.json's card, provenance and metrics of a pretrained model (`data`: the training
    set after size normalization; `delta` the SN shift of l, w, h in m, or None)."""
    card = ModelCard(
        detector=config.name,
        stage="pretrain",
        source_sensor=data.sensor,
        source_mount_height_m=data.mount_height_m,
        source_mean_lwh_m=tuple(float(v) for v in source_mean),
        size_norm=size_norm,
        sn_delta_lwh_m=None if delta is None else tuple(float(v) for v in delta),
        ros_range=tuple(ros_range) if size_norm == "ros" else None,
        target_profile=target_profile,
    )
    provenance = {
        "stage": "pretrain",
        "source": str(source),
        "source_hash": content_hash(source),
        "source_sensor": data.sensor,
        "size_norm": size_norm,
        "target_profile": target_profile,
        "sn_delta_lwh": None if delta is None else delta.tolist(),
        "ros_range": list(ros_range) if size_norm == "ros" else None,
        "seed": seed,
    }
    metrics = {
        "source_mean_lwh_m": source_mean.tolist(),
        "trained_mean_lwh_m": data.mean_lwh().tolist(),
        "frames": len(data),
        "boxes": data.num_boxes,
        "database_instances": 0 if data.database is None else len(data.database),
    }
    return {"card": card.to_dict(), "provenance": provenance, "metrics": metrics}


def check_config_overrides(config_overrides: dict | None) -> None:
    """DetectorConfig fields to override must make a valid config (checked before training)."""
    if config_overrides:
        from dali_cli.detector.config import DetectorConfig

        try:
            DetectorConfig.from_dict(config_overrides)
        except (TypeError, ValueError) as error:
            raise ParameterError("config_overrides", f"detector config: {error}") from None
