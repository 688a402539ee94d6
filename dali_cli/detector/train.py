"""The training loop: AdamW with a one-cycle learning rate, batches drawn from one or more labelled
sets in a fixed interleaving (e.g. source, pseudo, source, ...), an epoch or wall-clock budget,
a resumable state file, and a log row per logged step."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from dali_cli.detector.data import Augmentation, LabeledFrames
from dali_cli.detector.distributed import (
    SINGLE,
    World,
    broadcast_float,
    broadcast_object,
    mean_over_ranks,
    rank_slice,
    wrap,
)
from dali_cli.detector.loader import (
    Batch,
    StepBatches,
    TrainingSamples,
    batch_indices,
    collate,
    default_loader_workers,
    interleave,
    start_loader,
    step_frames,
    stop_loader,
    training_loader,
)
from dali_cli.detector.model import PillarCenterNet
from dali_cli.detector.refine import refine_loss
from dali_cli.detector.targets import detection_loss, peak_boxes
from dali_cli.runtime.errors import StageError
from dali_cli.runtime.machine import runtime_info, training_threads
from dali_cli.store.artifacts import ArtifactError

__all__ = ["batch_indices", "interleave"]  # the sampler's parts, where they always were

REFINE_STREAM = 7_919  # random stream of the refiner's jittered boxes, apart from the samples'


@dataclass
class TrainSettings:
    """Budget and optimizer settings. Exactly one of epochs / minutes is used (minutes wins).

    An epoch is one pass over the first data set; the others are interleaved by `mix`.
    With `minutes`, the learning-rate schedule follows the elapsed fraction of the budget.
    """

    epochs: float = 10.0
    minutes: float | None = None
    batch_size: int = 1
    lr: float = 5e-3
    weight_decay: float = 0.01
    pct_start: float = 0.3
    grad_clip: float = 10.0
    seed: int = 0
    precision: str = "fp32"  # "bf16" autocast: on CUDA, or on CPUs with AMX / AVX512-BF16
    threads: int | None = None  # None: this process's share of the cores (runtime.training_threads)
    # DataLoader worker processes making the batches (None: loader.default_loader_workers;
    # 0: in the training process); the batches do not depend on it
    loader_workers: int | None = None
    device: str = "auto"  # auto | cpu | cuda | cuda:N (dali_cli.runtime.device.resolve_device)
    mix: tuple[int, ...] = (1,)
    log_every: int = 5
    checkpoint_every_s: float = 120.0


@dataclass
class TrainResult:
    steps: int
    frames: int
    seconds: float
    log: list[dict] = field(default_factory=list)
    resumed_from_step: int = 0
    runtime: dict = field(default_factory=dict)  # runtime.runtime_info: threads, CPU, torch


def one_cycle(
    progress: float, max_lr: float, pct_start: float, div: float = 10.0, final_div: float = 1e3
) -> float:
    """One-cycle learning rate at `progress` in [0, 1]: cosine up from max/div, cosine down to max/final_div."""
    progress = min(max(progress, 0.0), 1.0)
    if progress < pct_start:
        t, start, end = progress / pct_start, max_lr / div, max_lr
    else:
        t, start, end = (progress - pct_start) / (1 - pct_start), max_lr, max_lr / final_div
    return end + (start - end) * (1 + math.cos(math.pi * t)) / 2


def schedule_lr(fraction: float, settings: TrainSettings) -> float:
    """Learning rate when `fraction` in [0, 1] of this run's budget is spent (one-cycle)."""
    return one_cycle(fraction, settings.lr, settings.pct_start)


def total_steps(datasets: list[LabeledFrames], settings: TrainSettings, world_size: int = 1) -> int:
    """Optimizer steps of an epoch budget; a step takes batch_size frames on each of
    `world_size` ranks (the global batch)."""
    pattern = interleave(settings.mix)
    global_batch = settings.batch_size * world_size
    per_epoch = math.ceil(len(datasets[0]) / global_batch) * len(pattern) / pattern.count(0)
    return max(1, math.ceil(settings.epochs * per_epoch))


def train(
    net: PillarCenterNet,
    datasets: list[LabeledFrames],
    augmentations: list[Augmentation],
    settings: TrainSettings,
    resume_path: str | Path | None = None,
    resume_key: str = "",
    progress: bool = True,
    on_log: Callable[[dict], None] | None = None,
    *,
    device: torch.device | None = None,
    world: World = SINGLE,
) -> TrainResult:
    """Train `net` in place on `device` (default: settings.device resolved). Saves a resumable
    state to `resume_path` every `checkpoint_every_s` and resumes from it when its `resume_key`
    matches (the caller's hash of inputs + parameters).

    With a distributed `world` (torchrun, see distributed.py) each rank trains on its slice of
    the global batch (batch_size frames per rank) through DistributedDataParallel; rank 0 alone
    saves resume states and shows progress, and every rank leaves with the same weights."""
    device, threads = training_device(settings, device, world)
    check_training_inputs(datasets, augmentations, settings, world)
    budget_s = settings.minutes * 60 if settings.minutes else None
    steps = None if budget_s else total_steps(datasets, settings, world.size)
    net.to(device)
    # net itself serially; under torchrun its batch norms synchronised and the whole in
    # DistributedDataParallel: before the optimizer, which must hold the synchronised layers' weights
    model = wrap(net, world)
    optimizer = torch.optim.AdamW(
        net.parameters(), lr=settings.lr, weight_decay=settings.weight_decay
    )
    resume_path = Path(resume_path) if resume_path else None
    step, elapsed, log = resume_training(resume_path, resume_key, net, optimizer, world)
    resumed_from = step
    net.train()
    forward = model
    bar = progress_bar(steps, budget_s, step, elapsed, world, progress)
    mine = rank_slice(world, settings.batch_size)  # this rank's positions in the global batch
    global_batch = settings.batch_size * world.size
    workers = (
        default_loader_workers(world.local_size, device.type, threads)
        if settings.loader_workers is None
        else settings.loader_workers
    )
    loader = training_loader(
        TrainingSamples(datasets, augmentations, settings.seed),
        StepBatches([len(d) for d in datasets], settings.mix, global_batch, mine, settings.seed,
                    start=step, stop=steps),
        net.config, workers, pin_memory=device.type == "cuda",
    )  # fmt: skip
    batches = start_loader(loader)
    last_save = time.perf_counter()
    window_frames, window_time, window_wait = 0, 0.0, 0.0
    try:
        while (step < steps) if steps else (elapsed < budget_s):
            started = time.perf_counter()
            fraction = step / steps if steps else elapsed / budget_s
            lr = schedule_lr(fraction, settings)
            for group in optimizer.param_groups:
                group["lr"] = lr
            batch = next(batches)  # the wait for the input pipeline
            waited = time.perf_counter() - started
            terms = optimize_step(net, forward, optimizer, batch, settings, device, step, mine)
            step += 1
            took = time.perf_counter() - started
            elapsed = broadcast_float(elapsed + took, world) if budget_s else elapsed + took
            window_frames, window_time = window_frames + global_batch, window_time + took
            window_wait += waited
            bar.update(1 if steps else min(round(elapsed), bar.total) - bar.n)
            if step % settings.log_every == 0 or step == 1 or step == steps:
                row = log_row(step, batch.dataset, terms, lr, window_frames / max(window_time, 1e-9),
                              elapsed, window_wait / max(window_time, 1e-9))  # fmt: skip
                log.append(row)
                window_frames, window_time, window_wait = 0, 0.0, 0.0
                bar.set_postfix(
                    loss=f"{row['loss']:.3f}", fps=f"{row['frames_per_s']:.1f}",
                    wait=f"{row['data_wait_share']:.0%}", lr=f"{lr:.1e}",
                )  # fmt: skip
                if on_log and world.is_main:
                    on_log(row)
            due = time.perf_counter() - last_save > settings.checkpoint_every_s
            if world.is_main and resume_path and due:
                save_resume_state(resume_path, resume_key, net, optimizer, step, elapsed, log)
                last_save = time.perf_counter()
    finally:  # also when training fails or is interrupted
        stop_loader(batches)
    bar.close()
    net.eval()
    return TrainResult(
        steps=step,
        frames=step * global_batch,
        seconds=elapsed,
        log=log,
        resumed_from_step=resumed_from,
        runtime={**runtime_info(threads, device, world), "loader_workers": workers},
    )


def training_device(settings: TrainSettings, device, world: World):
    """(device, torch threads) of this process: `device` or settings.device resolved (for the
    local rank), its precision checked; torch's thread count set to this process's share."""
    from dali_cli.runtime.device import check_precision, resolve_device

    device = device if device is not None else resolve_device(settings.device, world.local_rank)
    check_precision(settings.precision, device)
    threads = training_threads(settings.threads, world.local_size)
    torch.set_num_threads(threads)
    return device, threads


def progress_bar(
    steps: int | None, budget_s: float | None, step: int, elapsed: float, world: World,
    progress: bool,
):  # fmt: skip
    """A bar of steps (epoch budget) or seconds (wall-clock budget), shown by rank 0 only."""
    from tqdm import tqdm

    return tqdm(
        total=steps if steps else round(budget_s),
        initial=step if steps else round(elapsed),
        desc="train" if not world.distributed else f"train (rank 0 of {world.size})",
        unit="step" if steps else "s",
        disable=not (progress and world.is_main),
        leave=False,
    )


def check_training_inputs(
    datasets: list[LabeledFrames], augmentations: list, settings: TrainSettings, world: World
) -> None:
    """One mix weight and one augmentation per data set, no empty set (ValueError otherwise)."""
    if len(datasets) != len(settings.mix) or len(augmentations) != len(datasets):
        raise ValueError("need one mix weight and one augmentation setting per data set")
    for d in datasets:
        if len(d) == 0:
            raise ValueError(f"training set {d.name} has no frames")


def resume_training(
    resume_path: Path | None, resume_key: str, net, optimizer, world: World
) -> tuple[int, float, list]:
    """(step, elapsed seconds, log) to continue from: rank 0's resume state when it was written
    with `resume_key` (weights and optimizer loaded into `net` and `optimizer` on every rank),
    else a fresh start."""
    state = None
    if world.is_main and resume_path and resume_path.is_file():
        from dali_cli.detector.infer import load_weights_only

        state = load_weights_only(resume_path, "a dali training state", RESUME_ADVICE)
        if not isinstance(state, dict) or not RESUME_FIELDS <= set(state):
            raise ArtifactError(f"{resume_path}: not a dali training state; {RESUME_ADVICE}")
        state = state if state.get("key") == resume_key else None
    state = broadcast_object(state, world)  # the other ranks resume from rank 0's file
    if state is None:
        return 0, 0.0, []
    try:
        net.load_state_dict(state["net"])
        optimizer.load_state_dict(state["optimizer"])
        step, elapsed, log = int(state["step"]), float(state["elapsed_s"]), list(state["log"])
    except (RuntimeError, TypeError, ValueError, KeyError, AttributeError) as error:
        first = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise ArtifactError(
            f"{resume_path}: does not fit this training ({first}); {RESUME_ADVICE}"
        ) from None
    return step, elapsed, log


RESUME_FIELDS = {"key", "net", "optimizer", "step", "elapsed_s", "log"}
RESUME_ADVICE = "delete that file's directory (OUT.resume) to train from the start"


def step_samples(
    datasets: list[LabeledFrames],
    augmentations: list[Augmentation],
    pattern: list[int],
    step: int,
    global_batch: int,
    settings: TrainSettings,
    mine,
) -> tuple[int, list]:
    """The data set of optimizer step `step` (the mix's interleaving) and this rank's augmented
    samples (data.Sample) of its batch, made here: what the training loader's batch of that
    step holds (frame j of the global batch drawn from (seed, step, j), whatever the rank)."""
    d, indices = step_frames([len(x) for x in datasets], pattern, step, global_batch, settings.seed)
    samples = TrainingSamples(datasets, augmentations, settings.seed)
    return d, [samples[(d, int(indices[j]), step, j)][1] for j in mine]


def optimize_step(
    net: PillarCenterNet, forward, optimizer, batch: Batch | list, settings: TrainSettings,
    device, step: int, mine,
) -> dict:  # fmt: skip
    """One optimizer step on `batch` (a loader.Batch, or a list of data.Sample collated here):
    forward, detection + refine losses, clipped backward; returns the loss terms (tensors)."""
    from dali_cli.runtime.device import autocast

    if isinstance(batch, list):
        batch = collate([(0, sample) for sample in batch], net.config)
    config = net.config
    blocking = not batch.points.is_pinned()
    points = batch.points.to(device, non_blocking=not blocking)  # (P, 4)
    batch_index = batch.batch_index.to(device, non_blocking=not blocking)  # (P,)
    targets = batch.targets.to(device)
    with autocast(device, settings.precision):  # bf16: the networks' matrix products
        maps = forward(points, batch_index, len(batch))  # float32 maps
        loss, terms = detection_loss(maps, targets, config)
        if net.refiner is not None:  # its point MLP is a third of a step's products
            frame_points = batch.frame_points
            if points.device.type != "cpu":  # crops and targets where the points already are
                frame_points = list(points.split([len(p) for p in batch.frame_points]))
            loss, terms = add_refine_loss(
                net, maps, frame_points, targets, loss, terms, settings.seed, step,
                positions=list(mine),
            )  # fmt: skip
    check_finite_loss(loss, terms, step)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(net.parameters(), settings.grad_clip)
    optimizer.step()
    return terms


class NonFiniteLossError(StageError):
    """The training loss became NaN or infinite: the weights would be ruined from here on."""


def check_finite_loss(loss: torch.Tensor, terms: dict, step: int) -> None:
    """Stop training at the first optimizer step (`step`, 0-based) whose loss is not finite,
    before its gradients touch the weights (NonFiniteLossError naming the step and the terms).
    One scalar read per step."""
    if bool(torch.isfinite(loss.detach()).item()):
        return
    shown = ", ".join(f"{name} {float(value):.4g}" for name, value in terms.items())
    raise NonFiniteLossError(
        f"training step {step + 1}: the loss is {float(loss.detach()):g} ({shown}); nothing was "
        "written. A learning rate too high (--lr) or box sizes far from the data's "
        "(--target-size, the labels) make it diverge"
    )


def log_row(
    step: int, dataset: int, terms: dict, lr: float, frames_per_s: float, elapsed: float,
    data_wait_share: float = 0.0,
) -> dict:  # fmt: skip
    """A train_log row: the loss terms averaged over the ranks, lr, throughput (all ranks) and
    the share of the step time this rank waited for its batch (the input pipeline)."""
    terms = {k: float(v) for k, v in mean_over_ranks(terms).items()}
    return {
        "step": step,
        "dataset": dataset,
        **terms,
        "lr": lr,
        "frames_per_s": frames_per_s,
        "elapsed_s": elapsed,
        "data_wait_share": data_wait_share,
    }


def add_refine_loss(
    net, maps, points_list, targets, loss, terms, seed: int, step: int, positions=None
):
    """`loss` plus the second stage's losses on the heads' strongest peaks (see refine.py).
    points_list: each frame's points, numpy (the reference crops) or tensors on the device (the
    crops and targets computed there, a GPU's step). Frame b's jitter draws are seeded by (seed,
    step, its position in the global batch)."""
    config = net.config
    _, boxes = peak_boxes(maps, config, config.refine_train_peaks)  # (B, k, 7)
    positions = range(len(points_list)) if positions is None else positions
    rngs = [np.random.default_rng([seed, step, REFINE_STREAM, j]) for j in positions]
    on_device = bool(points_list) and isinstance(points_list[0], torch.Tensor)
    proposals = list(boxes.detach()) if on_device else list(boxes.cpu().numpy())
    box, iou = refine_loss(net.refiner, points_list, proposals, targets.objects, config, rngs)
    w_box, w_iou = config.refine_weights
    total = loss + w_box * box + w_iou * iou
    return total, {
        **terms,
        "loss": total.detach(),
        "refine_box": box.detach(),
        "refine_iou": iou.detach(),
    }


def save_resume_state(
    path: Path, key: str, net, optimizer, step: int, elapsed: float, log: list
) -> None:
    """Everything needed to continue: weights, optimizer, step, elapsed time, log (atomic write)."""
    from dali_cli.store.atomic_file import write_atomically
    from dali_cli.store.disk_space import save_torch

    state = {
        "key": key,
        "net": net.state_dict(),
        "optimizer": optimizer.state_dict(),
        "step": step,
        "elapsed_s": elapsed,
        "log": log,
    }
    write_atomically(path, lambda temporary: save_torch(state, temporary))
