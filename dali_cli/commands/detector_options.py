"""Options of the commands that train or run the detector: the training budget and optimizer
(pretrain, retrain, self-train), --device/--precision, the inference threads and batch of the
stages that run the model on the target (ptsn-sweep, pseudo-label, eval), --score-min and
--target-profile; each defined once (the generic option kinds: common.py)."""

from __future__ import annotations

import click

from dali_cli.commands.common import (
    BATCH,
    FRACTION,
    SEED,
    apply_options,
    no_progress_option,
    sensors_option,
    stage_options,
    tuning_option,
)
from dali_cli.commands.kinds import EPOCHS, LEARNING_RATE, LOCAL_WORKERS, MINUTES


def device_options(function):
    """--device and --precision, shared by every command that runs the detector (pretrain,
    retrain, self-train, ptsn-sweep, pseudo-label, eval)."""
    function = tuning_option(
        "--precision",
        type=click.Choice(["fp32", "bf16"]),
        default="fp32",
        show_default=True,
        help="bf16 autocast: for CUDA GPUs with bf16 (Ampere or newer); on a CPU it is faster "
        "only with AMX / AVX512-BF16.",
    )(function)
    return click.option(
        "--device",
        default="auto",
        show_default=True,
        metavar="auto|cpu|cuda|cuda:N",
        help="Where the network runs. auto: CUDA when available, else the CPU. cuda under "
        "torchrun: the GPU of the local rank. A missing GPU is an error (nothing written).",
    )(function)


def training_options(function):
    """Budget, optimizer and input options shared by pretrain, retrain and self-train, with
    --device/--precision, --sensors and the stage switches."""
    options = [
        click.option(
            "--epochs",
            type=EPOCHS,
            default=10.0,
            show_default=True,
            help="Passes over the training frames (pretrain: the source; retrain: source and "
            "PPCG frames; self-train: the target).",
        ),
        click.option(
            "--minutes",
            type=MINUTES,
            default=None,
            help="Wall-clock training budget instead of --epochs; the learning-rate "
            "schedule follows the elapsed fraction of the budget.",
        ),
        click.option(
            "--seed",
            type=SEED,
            default=0,
            show_default=True,
            help="Seed of initialization, sampling and augmentation.",
        ),
        tuning_option(
            "--batch-size",
            type=BATCH,
            default=1,
            show_default=True,
            help="Frames per training step (per process under torchrun).",
        ),
        tuning_option(
            "--lr",
            type=LEARNING_RATE,
            default=5e-3,
            show_default=True,
            help="Peak learning rate of the one-cycle schedule (AdamW).",
        ),
        tuning_option(
            "--threads",
            type=BATCH,
            default=None,
            help="torch threads per process (default: every core this process may use, divided "
            "by the processes torchrun starts on this machine; recorded in the manifest).",
        ),
        tuning_option(
            "--loader-workers",
            type=LOCAL_WORKERS,
            default=None,
            help="Processes that read, augment and batch the training frames ahead of the "
            "training step (default on a GPU: the cores this process may use, less one, at "
            "most 8; on the CPU 1 when --threads leaves a core spare, else 0: in the training "
            "process, whose step uses every core). The batches do not depend on it; recorded in "
            "the manifest's runtime.",
        ),
        tuning_option(
            "--no-augment",
            "no_augment",
            is_flag=True,
            help="Disable gt-sampling, flip, rotation, scaling, object noise.",
        ),
        no_progress_option,
    ]
    return apply_options(function, [device_options, *options, sensors_option, stage_options])


def score_min_option(
    dest: str = "score_min", help: str = "Drop boxes scored below this.", flag: str = "--score-min"
):
    """--score-min: the score from which a box counts as a car (default SCORE_MIN); boxes below
    it are dropped. `flag` names a cut with another use (eval's --size-score-min)."""
    from dali_cli.labels import SCORE_MIN

    return click.option(
        flag,
        dest,
        type=FRACTION,
        default=SCORE_MIN,
        show_default=True,
        help=help,
    )


def target_profile_option(dest: str = "target_profile"):
    """--target-profile: the sensor profile (a sensors.toml name) of the target frame set a
    stage reads (default: the one recorded with the frames)."""
    return click.option(
        "--target-profile",
        dest,
        default=None,
        help="Target sensor profile (default: the frame set's).",
    )


def inference_threads_option(function):
    """--threads of the commands that run the detector on frames (ptsn-sweep, pseudo-label,
    eval): torch threads in the stage's own process (workers run one each)."""
    return tuning_option(
        "--threads",
        type=BATCH,
        default=None,
        help="torch threads of the detector in this process (default: every core this process "
        "may use; --workers > 1: one per worker). The boxes' last bits follow the thread count: "
        "give it to reproduce a run on another machine (recorded in the manifest's runtime).",
    )(function)


def target_scaling_options(function):
    """--batch-size and --no-progress of the commands that run the model on the target scaled
    about the ground (ptsn-sweep, pseudo-label; the pivot is the target profile's mount height),
    with --device/--precision, --sensors and the stage switches."""
    options = [
        tuning_option(
            "--batch-size",
            type=BATCH,
            default=8,
            show_default=True,
            help="Frames per detector pass (the output does not depend on it).",
        ),
        inference_threads_option,
        no_progress_option,
        device_options,
        sensors_option,
        stage_options,
    ]
    return apply_options(function, options)


def pop_training(options: dict):
    """The TrainingOptions of a training command's parsed `options` (training_options), which
    are removed from `options`; the rest are the stage's own."""
    from dali_cli.detector.training_stage import TrainingOptions

    return TrainingOptions(
        epochs=options.pop("epochs"),
        minutes=options.pop("minutes"),
        seed=options.pop("seed"),
        batch_size=options.pop("batch_size"),
        lr=options.pop("lr"),
        precision=options.pop("precision"),
        threads=options.pop("threads"),
        loader_workers=options.pop("loader_workers"),
        augment=not options.pop("no_augment"),
        device=options.pop("device"),
        progress=not options.pop("no_progress"),
    )


def run_training_command(stage: str, run, *args, extra: str = "", **options) -> None:
    """Run a training stage function `run(*args, training=..., **rest)` from a command's parsed
    options and print its one line: steps and frames seen (+ `extra`, formatted with the
    manifest's counts)."""
    outcome = run(*args, training=pop_training(options), **options)
    if outcome.status == "ran":
        counts = (outcome.manifest or {}).get("outputs", {}).get("counts", {})
        click.echo(
            f"{stage}: {counts.get('steps')} steps, {counts.get('frames_seen')} frames seen"
            + (extra.format(**counts) if extra else "")
        )
