"""The training body the pretrain, retrain and self-train stages share: resume handling, the
checkpoint's metadata and training summary, the training log, and `run_training_stage` (the
manifest contract around one training run). torch is imported only when a model is trained."""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import asdict
from pathlib import Path

import numpy as np

from dali_cli.manifest import BuildResult, StageOutcome, content_hash, run_stage


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
) -> BuildResult:
    """The training body pretrain, retrain and self-train share: train `net` on `datasets`,
    write model.pt + model.json (`meta` plus the training summary) + train_log.parquet into
    `tmp`, and return the manifest's counts, timings and runtime (threads, CPU model, torch)."""
    from dali_cli.detector import save_checkpoint, train

    result = train(net, datasets, augmentations, settings, resume, key, progress=progress)
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


def run_training_stage(
    stage: str,
    out: Path,
    inputs: dict,
    params: dict,
    train_fn,
    force: bool,
    dry_run: bool,
    seed: int,
) -> StageOutcome:
    """run_stage around `train_fn(tmp_dir, resume_path, resume_key) -> BuildResult`, then drop
    the resume state once the checkpoint is in place."""
    resume = resume_path_for(out)

    def build(tmp: Path) -> BuildResult:
        key = resume_key(inputs, params)
        return train_fn(tmp, resume, key)

    outcome = run_stage(stage, out, inputs, params, build, force=force, dry_run=dry_run, seed=seed)
    if outcome.status == "ran":
        shutil.rmtree(resume.parent, ignore_errors=True)
    return outcome
