"""The training body the pretrain, retrain and self-train stages share: resume handling, the
checkpoint's metadata and training summary, the training log, and `run_training_stage` (the
manifest contract around one training run, on a device, under torchrun with DDP when launched
so). It lives with the detector: importing it imports the detector package (and torch)."""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from dali_cli.runtime import console
from dali_cli.runtime.errors import ParameterError
from dali_cli.store.manifest import BuildResult, StageOutcome, content_hash, run_stage


@dataclass(frozen=True)
class TrainingOptions:
    """The training budget, optimizer and runtime pretrain, retrain and self-train share
    (the commands' training options). Exactly one of epochs / minutes is used (minutes wins)."""

    epochs: float = 10.0
    minutes: float | None = None
    seed: int = 0
    batch_size: int = 1
    lr: float = 5e-3
    precision: str = "fp32"
    threads: int | None = None  # None: this process's share of the cores
    loader_workers: int | None = None  # None: loader.default_loader_workers; 0: in process
    augment: bool = True
    device: str = "auto"  # auto | cpu | cuda | cuda:N
    progress: bool = True

    def params(self) -> dict:
        """The manifest parameters they set (threads, device and progress do not change the
        model: they are recorded in the manifest's runtime, not here)."""
        params = {
            "epochs": None if self.minutes else self.epochs,
            "minutes": self.minutes,
            "seed": self.seed,
            "batch_size": self.batch_size,
            "lr": self.lr,
            "precision": self.precision,
            "compile": False,  # a retired option, recorded so earlier manifests stay up to date
            "augment": self.augment,
        }
        return params

    def settings(self, **extra):
        """dali_cli.detector.TrainSettings of these options (`extra`: e.g. mix)."""
        from dali_cli.detector import TrainSettings

        return TrainSettings(
            epochs=self.epochs, minutes=self.minutes, batch_size=self.batch_size, lr=self.lr,
            seed=self.seed, precision=self.precision,
            threads=self.threads, device=self.device,
            loader_workers=self.loader_workers, **extra,
        )  # fmt: skip

    def augmentation(self):
        """The default augmentation, or none when augmentation is off."""
        from dali_cli.detector import Augmentation

        return Augmentation() if self.augment else Augmentation.none()


def target_car_size(
    target_profile: str | None,
    target_size: tuple[float, float, float] | None,
    sensors_path,
    needed_by: str,
) -> tuple[float, float, float]:
    """The target's mean car size (l, w, h in m) a training stage shifts source boxes to:
    `target_size`, else `target_profile`'s car_mean_lwh_m; a ParameterError naming both
    (`needed_by`: what needs it) without either."""
    if target_size is not None:
        return target_size
    if target_profile is None:
        raise ParameterError(
            ("target_profile", "target_size"), f"{needed_by} needs the target's car size"
        )
    from dali_cli.sensors import get_profile

    return tuple(get_profile(target_profile, sensors_path).car_mean_lwh_m)


def seeded_network(config, seed: int, weights=None):
    """A PillarCenterNet of `config` initialized from torch seed `seed`, then given `weights`
    (a state dict) when not None (the seeded draw happens either way, as the stages always
    did, so a run's random stream does not depend on where its weights come from)."""
    import torch

    from dali_cli.detector import PillarCenterNet

    torch.manual_seed(seed)
    net = PillarCenterNet(config)
    if weights is not None:
        net.load_state_dict(weights)
    return net


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
    settings = asdict(settings)
    settings.pop("loader_workers")  # the runtime records it: it does not change the model
    return {
        "steps": result.steps,
        "frames": result.frames,
        "seconds": round(result.seconds, 1),
        "frames_per_s": round(result.frames / max(result.seconds, 1e-9), 2),
        "resumed_from_step": result.resumed_from_step,
        "final_loss": float(np.mean([r["loss"] for r in tail])) if tail else None,
        "settings": settings,
        "runtime": result.runtime,
    }


def attach_database(data, config, augment: bool) -> None:
    """Give `data` its gt-sampling database (its own boxes inside the detection region), or
    none when augmentation is off: built in memory for points in memory, else read from (or
    built once into) the on-disk cache of dali_cli.detector.gt_database, memory-mapped."""
    from dali_cli.detector.augment import ObjectDatabase
    from dali_cli.detector.data import detection_region
    from dali_cli.detector.gt_database import cached_database

    if not augment:
        data.database = None
    elif isinstance(data.points, list):
        data.database = ObjectDatabase.build(
            data.points, data.boxes, region=detection_region(config)
        )
    else:
        data.database = cached_database(data, region=detection_region(config))


@dataclass
class PreparedTraining:
    """What a training stage hands the shared body: the network to train, its data sets with
    their augmentations (the first one's frames define an epoch), the TrainSettings, and the
    checkpoint's `meta` (card, provenance, metrics), the manifest's counts and notes."""

    net: object
    datasets: list
    augmentations: list
    settings: object
    meta: dict
    counts: dict
    notes: list[str]


def fit_and_save(
    tmp: Path | None,
    job: PreparedTraining,
    resume: Path,
    key: str,
    *,
    load_s: float,
    progress: bool,
    world=None,
) -> BuildResult | None:
    """The training body pretrain, retrain and self-train share: train `job.net` on its data
    sets on `world` (its device; the ranks of a torchrun run), write model.pt + model.json
    (`job.meta` plus the training summary) + train_log.parquet into `tmp`, and return the
    manifest's counts, timings and runtime (threads, device, world size, CPU/GPU model, torch).
    A rank other than 0 of a distributed run trains with the others and writes nothing (`tmp`
    None)."""
    from dali_cli.detector import save_checkpoint, train
    from dali_cli.detector.distributed import SINGLE

    world = world or SINGLE
    if tmp is not None:  # refused before it trains, not after
        check_training_space(tmp.parent, job.net)
    result = train(
        job.net, job.datasets, job.augmentations, job.settings, resume, key, progress=progress,
        device=world.device, world=world,
    )  # fmt: skip
    report_ranks(result, world)
    if tmp is None:
        return None
    save_checkpoint(tmp, job.net, {**job.meta, "train": training_summary(result, job.settings)})
    write_train_log(tmp, result.log)
    notes = job.notes
    if result.resumed_from_step:
        notes = [*notes, f"resumed from step {result.resumed_from_step}"]
    return BuildResult(
        counts={**job.counts, "steps": result.steps, "frames_seen": result.frames},
        timings={"load_seconds": round(load_s, 2), "train_seconds": round(result.seconds, 2)},
        notes=notes,
        extra={"runtime": result.runtime},
    )


# model.pt once, the resume state (weights and AdamW's two moments) twice while it is rewritten
TRAINING_SPACE_FACTOR = 1 + 2 * 3
TRAINING_SPACE_MARGIN = 1 << 20  # the training log, model.json, the manifest


def training_space(net) -> int:
    """Bytes a training run of `net` may write beside its output: its weights' size (4 bytes
    a parameter in fp32) x TRAINING_SPACE_FACTOR, plus a margin for the small files."""
    from dali_cli.store.disk_space import tensor_bytes

    return tensor_bytes(net.state_dict()) * TRAINING_SPACE_FACTOR + TRAINING_SPACE_MARGIN


def check_training_space(directory: Path, net) -> None:
    """A DiskSpaceError naming `directory` when its disk cannot hold what training `net`
    writes there (training_space): a full disk is found before the training, not after."""
    from dali_cli.store.disk_space import DiskSpaceError, free_bytes

    needed, free = training_space(net), free_bytes(directory)
    if free is not None and free < needed:
        raise DiskSpaceError(
            f"{directory}, for model.pt and the training's resume state", needed, free
        )


def report_ranks(result, world) -> None:
    """One log line per rank: which engine, and what this rank did."""
    runtime = result.runtime
    engine = (
        f"rank {world.rank} of {world.size} ({world.backend}, DDP)"
        if world.distributed
        else "1 process"
    )
    console.info(
        f"train: {engine} on {runtime.get('device')}, {runtime.get('threads')} threads: "
        f"{result.steps} steps, {result.frames} frames (all ranks) in {result.seconds:.1f} s"
    )


def run_training_stage(
    stage: str,
    out: Path,
    inputs: dict,
    params: dict,
    prepare,
    force: bool,
    dry_run: bool,
    training: TrainingOptions,
) -> StageOutcome:
    """run_stage around one training run: `prepare() -> PreparedTraining` loads the data and
    builds the network (timed as loading), fit_and_save trains it and writes the checkpoint;
    then the resume state is dropped once the checkpoint is in place. `params` are the stage's own
    parameters; the training options' are added to them.

    `training.device` (auto | cpu | cuda | cuda:N) is resolved first: a missing GPU fails before anything
    is written. Under torchrun (dali_cli.detector.distributed) rank 0 runs the stage as usual and
    tells the other ranks whether to train; they train with it and write nothing, and rank 0
    commits only after every rank finished (a failing rank fails the stage, no artifact)."""
    from dali_cli.detector import distributed
    from dali_cli.runtime.device import resolve_device

    world = distributed.launched()
    params = {**params, **training.params()}
    seed = training.seed
    torch_device = resolve_device(training.device, world.local_rank if world.distributed else None)
    if world.distributed:  # the global batch is batch_size x world size: another training
        params = {**params, "world_size": world.size}
    resume = resume_path_for(out)
    key = None

    def train_fn(tmp: Path | None, resume: Path, key: str | None, world) -> BuildResult | None:
        started = time.perf_counter()
        job = prepare()
        load_s = time.perf_counter() - started
        return fit_and_save(
            tmp, job, resume, key, load_s=load_s, progress=training.progress, world=world
        )

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
