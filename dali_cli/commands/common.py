"""Options and helpers shared by the stage commands: every option two commands share is
defined here once (the stage switches, --out, --sensors, --device, --executor, the training
budget, the target-scaling options of ptsn-sweep and pseudo-label), plus small factories for
the common option kinds (an existing input directory, a choice with a shown default)."""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import click

from dali_cli.commands.kinds import CAR_SIZE, EPOCHS, LEARNING_RATE, LOCAL_WORKERS, MINUTES

INPUT_DIR = click.Path(exists=True, file_okay=False)
"""An existing directory (a frame set, a model, a library...)."""


def input_dir_option(*decls: str, help: str, required: bool = True):
    """An existing input directory, required unless told otherwise."""
    return click.option(*decls, type=INPUT_DIR, required=required, help=help)


class AliasedOption(click.Option):
    """An option whose later long names are its former names, kept working for one release
    (`aliases` of `renamed_option`): --help lists only the first."""

    def get_help_record(self, ctx: click.Context):
        names, self.opts = self.opts, self.opts[:1]
        try:
            return super().get_help_record(ctx)
        finally:
            self.opts = names

    def get_error_hint(self, ctx: click.Context) -> str:
        return f"'{self.opts[0]}'"


def renamed_option(name: str, *aliases_and_dest: str, **kwargs):
    """click.option(name, ...) that also answers to its former names (the `--` words among
    `aliases_and_dest`) without listing them in --help."""
    return click.option(name, *aliases_and_dest, cls=AliasedOption, **kwargs)


def data_option(dest: str, help: str):
    """--data DIR: the frame set a command runs on (every stage that reads one, under one name;
    --target is its former name in the target stages)."""
    return renamed_option("--data", "--target", dest, type=INPUT_DIR, required=True, help=help)


def out_dir_option(help: str = "Output directory.", *decls: str):
    """--out DIR: the artifact directory a stage writes (atomically)."""
    return click.option("--out", *decls, type=click.Path(file_okay=False), required=True, help=help)


def choice_option(
    *decls: str, choices: list[str], default: str | None, help: str, tuning: bool = False
):
    """One of `choices`, with the default shown in --help (a tuning option with `tuning`)."""
    option = tuning_option if tuning else click.option
    return option(*decls, type=click.Choice(choices), default=default, show_default=True, help=help)


# Tuning options: settings of an algorithm whose defaults were measured (docs/RESULTS.md,
# docs/ptsn.md, docs/ppcg.md) and that only research changes, and the engine's fine controls
# (threads, batch sizes, loader processes, the executor and a Ray cluster's address, bf16
# precision, the progress bar, another sensors.toml). They
# work like any option but stay out of `--help` unless the environment has DALI_HELP=all, so that
# a command's help shows what running the pipeline needs; each such command says so below its
# options (TUNING_NOTE, added by StageCommand).
SHOW_TUNING = os.environ.get("DALI_HELP", "") == "all"
TUNING_NOTE = (
    "Tuning options (the algorithm's measured defaults, for research) and the engine's fine "
    "controls (threads, batch sizes, executor, precision, progress bar, another sensors.toml) "
    "are listed with: "
    "DALI_HELP=all dali COMMAND --help"
)
# the options that say where and how a command runs, not what it computes: listed in their own
# section of --help ("Engine options"); each is defined once, below
ENGINE_PARAMS = {
    "device", "precision", "executor", "workers", "ray_address", "threads", "batch_size",
    "loader_workers", "no_progress", "sensors_path",
}  # fmt: skip


def tuning_option(*decls: str, **kwargs):
    """A click option of the tuning group: hidden from the default --help (see SHOW_TUNING)."""
    return click.option(*decls, hidden=not SHOW_TUNING, **kwargs)


def named_hidden_options(command: click.Command, ctx: click.Context) -> list[click.Option]:
    """The hidden (tuning) options of `command` whose name its help text, epilog or visible
    options' help mention (a whole word, e.g. `--nms-iou`): the default --help shows them too,
    so that every option a help text names is visible where it is named."""
    visible = [p for p in command.get_params(ctx) if not getattr(p, "hidden", False)]
    text = " ".join(
        [command.help or "", command.epilog or ""]
        + [getattr(p, "help", None) or "" for p in visible]
    )
    named = []
    for param in command.get_params(ctx):
        if isinstance(param, click.Option) and param.hidden:
            names = [*param.opts, *param.secondary_opts]
            if any(re.search(rf"(?<![\w-]){re.escape(name)}(?![\w-])", text) for name in names):
                named.append(param)
    return named


class StageCommand(click.Command):
    """A command whose --help lists its engine options (ENGINE_PARAMS) in a section of their
    own after the others, the tuning options its text names (`named_hidden_options`) in a
    third, and ends with TUNING_NOTE when some of its options are hidden. dali_cli.cli gives
    every subcommand this class."""

    def format_options(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        own, engine, named = [], [], []
        for param in self.get_params(ctx):
            record = param.get_help_record(ctx)
            if record is not None:
                (engine if param.name in ENGINE_PARAMS else own).append(record)
        for param in named_hidden_options(self, ctx):
            param.hidden = False  # click gives no help record for a hidden option
            try:
                named.append(param.get_help_record(ctx))
            finally:
                param.hidden = True
        sections = (("Options", own), ("Engine options", engine),
                    ("Tuning options named above", named))  # fmt: skip
        for title, records in sections:
            if records:
                with formatter.section(title):
                    formatter.write_dl(records)

    def format_epilog(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        super().format_epilog(ctx, formatter)
        if any(getattr(param, "hidden", False) for param in self.params):
            formatter.write_paragraph()
            with formatter.indentation():
                formatter.write_text(TUNING_NOTE)


def ran_counts(outcome) -> dict | None:
    """The output counts of a stage that ran (a StageOutcome's manifest), for the one-line summary
    a command prints; None when it was up to date or a dry run."""
    if outcome.manifest and outcome.status == "ran":
        return outcome.manifest["outputs"]["counts"]
    return None


def stage_command_class(command: click.Command) -> click.Command:
    """`command` and, for a group, each of its subcommands, as StageCommands (help layout only)."""
    if isinstance(command, click.Group):
        for sub in command.commands.values():
            stage_command_class(sub)
    elif type(command) is click.Command:
        command.__class__ = StageCommand
    return command


class FiniteFloat(click.FloatRange):
    """A finite float (NaN and ±inf refused), optionally within a range: click's FloatRange
    lets NaN through every bound (NaN compares false) and accepts inf."""

    name = "float"

    def convert(self, value, param, ctx):
        number = click.FLOAT.convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        return super().convert(number, param, ctx)


FINITE = FiniteFloat()
"""Any finite float."""
POSITIVE = FiniteFloat(min=0, min_open=True)
"""A finite float > 0."""
NON_NEGATIVE = FiniteFloat(min=0)
"""A finite float >= 0."""
FRACTION = FiniteFloat(0, 1)
"""A finite float in [0, 1]."""


def finite_range(
    min: float | None = None,
    max: float | None = None,
    *,
    min_open: bool = False,
    max_open: bool = False,
) -> FiniteFloat:
    """A finite float within [min, max] (open ends as told)."""
    return FiniteFloat(min, max, min_open=min_open, max_open=max_open)


SEED = click.IntRange(0, 2**32 - 1)
"""A random seed: what numpy and torch both accept."""
COUNT_LIMIT = 4096
BATCH = click.IntRange(1, COUNT_LIMIT)
"""Frames per batch, workers, threads: at least 1, at most COUNT_LIMIT (more would only
exhaust memory or processes before the first step)."""


def target_size_options(profile_help: str, size_help: str):
    """--target-profile and --target-size 'l,w,h': the target's mean car size (pretrain's SN,
    retrain's --size-norm sn)."""

    def decorate(function):
        function = click.option("--target-size", type=CAR_SIZE, default=None, help=size_help)(
            function
        )
        return click.option("--target-profile", default=None, help=profile_help)(function)

    return decorate


def apply_options(function, options: list):
    """Decorate `function` with `options` so they list in --help in the given order."""
    for option in reversed(options):
        function = option(function)
    return function


def stage_options(function):
    """--force and --dry-run, the two switches every stage command has."""
    function = click.option(
        "--dry-run", is_flag=True, help="Print whether the stage would run, and why; write nothing."
    )(function)
    function = click.option(
        "--force", is_flag=True, help="Rerun even when the output is up to date."
    )(function)
    return function


def scale_from_option(tuning: bool = False):
    """--scale-from: the PTSN scale ŝ of a `dali ptsn-sweep` directory or its scale.json, one
    option with one meaning for every command that runs the detector at a scale."""
    option = tuning_option if tuning else click.option
    return option(
        "--scale-from",
        type=click.Path(exists=True),
        default=None,
        help="A ptsn-sweep directory (or its scale.json): run at its 'scale', ŝ.",
    )


def sensors_option(function, *, shown: bool = False):
    """--sensors FILE: another sensors.toml (an engine control, listed with DALI_HELP=all unless
    `shown`: `dali sensors` lists the file's profiles)."""
    option = click.option if shown else tuning_option
    return option(
        "--sensors",
        "sensors_path",
        type=click.Path(exists=True, dir_okay=False),
        default=None,
        help="sensors.toml to use instead of the project's.",
    )(function)


def artifact_options(help: str = "Output directory.", *, progress: bool = True):
    """--out DIR (out_dir_option), --no-progress unless not `progress`, and the stage switches:
    the options of every command whose stage writes one artifact directory."""
    options = [out_dir_option(help), *([no_progress_option] if progress else []), stage_options]
    return lambda function: apply_options(function, options)


def model_target_out_options(model_help: str):
    """--model, --data and --out of the stages that run a model on the target frame set."""

    def decorate(function):
        function = out_dir_option()(function)
        function = data_option(
            "target_dir", "Target frame set (frames.zarr). Its labels, if any, are never read."
        )(function)
        return click.option(
            "--model",
            "model_dir",
            required=True,
            type=click.Path(exists=True, file_okay=False),
            help=model_help,
        )(function)

    return decorate


def output_options(function):
    """--out DIR, --sensors and the stage switches of commands that write one artifact."""
    return apply_options(function, [out_dir_option(), sensors_option, stage_options])


def import_options(default_sensor: str | None):
    """--sensor (the profile recorded with imported frames; required when None) + output_options
    and --no-progress. The commands hand --sensors / --force / --dry-run on to their stage as
    `**run` (dali_cli.importers.common.ImportRun)."""

    def decorate(function):
        function = output_options(no_progress_option(function))
        if default_sensor is None:
            return click.option(
                "--sensor", required=True, help="Sensor profile of the data (a sensors.toml name)."
            )(function)
        return tuning_option(
            "--sensor",
            default=default_sensor,
            show_default=True,
            help="Sensor profile recorded with the frames.",
        )(function)

    return decorate


BEAMS_NOTE = (
    "--beams 32 or 16 thins each scan to that many of its 64 beams, a sparser LiDAR's stand-in "
    "(the frames' sensor becomes kitti-32 or kitti-16)."
)


def beams_options(function):
    """--beams and --beams-azimuth-half of the KITTI imports (kitti, kitti-raw, kitti-odometry;
    dali_cli.importers.beams.BeamThinning): handed to their stage as `beams` and
    `beams_azimuth_half`. Both are tuning options (a research protocol); each command's text
    names --beams (BEAMS_NOTE, added to its help here), so that its default --help lists it."""
    function.__doc__ = f"{(function.__doc__ or '').rstrip()}\n\n    {BEAMS_NOTE}\n"
    function = tuning_option(
        "--beams-azimuth-half",
        is_flag=True,
        help="With --beams 32 or 16: also keep every 2nd point of each kept beam, in azimuth "
        "order (the protocol's 32* and 16*; sensor kitti-N-half).",
    )(function)
    return tuning_option(
        "--beams",
        type=click.Choice(["64", "32", "16"]),
        default="64",
        show_default=True,
        callback=lambda _ctx, _param, value: int(value),
        help="Beams of the 64 to keep per scan, a sparser LiDAR's stand-in (LiDAR Distillation, "
        "Wei et al. 2022): each scan's points are clustered into 64 beams by k-means of their "
        "elevation angle and beams 0, 2, 4, ... (32) or 0, 4, 8, ... (16), counted from the "
        "lowest, are kept. The frames' sensor becomes kitti-32 / kitti-16.",
    )(function)


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


def workers_option(local_default: str):
    """--workers N: processes (local) or actors (ray) that run the stage's frames."""
    return click.option(
        "--workers",
        type=BATCH,
        default=None,
        help=f"Workers: processes of this machine (--executor local; default {local_default}) or "
        "Ray actors (--executor ray; default one per CPU of the cluster). The output does not "
        "depend on it.",
    )


def executor_options(function):
    """--executor local|ray and --ray-address: the engine that runs a per-frame stage's shards
    (dali_cli.executors; docs/scale-out.md)."""
    function = tuning_option(
        "--ray-address",
        default=None,
        metavar="ADDR",
        help="With --executor ray: the Ray cluster to use (e.g. HEAD:6379 of `ray start "
        "--head`, or 'auto'). Default: start a local Ray instance for this run.",
    )(function)
    return tuning_option(
        "--executor",
        type=click.Choice(["local", "ray"]),
        default="local",
        show_default=True,
        help="Engine for the per-frame work: local = this machine (in-process for one worker, "
        "else a process pool); ray = Ray actors, each loading its models once, writing shards "
        "into the output's temporary directory (needs pip install -e '.[ray]'). The output "
        "does not depend on it.",
    )(function)


def no_progress_option(function):
    """--no-progress, the one switch of every command that draws a progress bar (an engine
    control: listed with DALI_HELP=all)."""
    return tuning_option("--no-progress", is_flag=True, help="No progress bar.")(function)


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
            "process, whose step uses every core). The batches do not depend on it; recorded in the "
            "manifest's runtime.",
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


PROTOCOLS_HELP = """\b
Protocols: kitti = easy/moderate/hard from the KITTI label fields (2D box height, occlusion,
truncation); range = all boxes and BEV-distance bands 0-30, 30-50, 50-80 m; st3d = ST3D's
target-domain evaluation (ground truth only in the front 90 deg FOV and the detection range,
every box 'easy'); auto (default) = kitti when the ground truth has the KITTI fields, else range.
dali synth labels carry the KITTI fields (2D box, truncation, occlusion level of a virtual KITTI
camera at the sensor), so --protocol kitti gives easy/moderate/hard on synthetic data too.
Van ground truths are ignored for Car. Of the tuning options (shown above): --front-only
restricts any protocol to that front region, ground truth and predictions alike (KITTI's clouds
are FOV-cropped; dali synth's are 360 degrees); --min-gt-points marks ground-truth cars with
fewer points as ignored (neither miss nor false positive), it never drops them;
--recall-positions 400 reads the precision at exact recalls (sets of fewer than 41 cars).
"""


def calib_option(help: str):
    """--calib: KITTI camera calibration (importers/calibration.py: a calib .txt for every
    frame, a raw drive's date folder, or a folder of <frame>.txt), a Path or None."""
    return click.option(
        "--calib", type=click.Path(exists=True, path_type=Path), default=None,
        help="KITTI calibration: a calib .txt for every frame, a folder of <frame>.txt, or a raw "
             "drive's date folder (holding calib_cam_to_cam.txt, calib_velo_to_cam.txt). " + help,
    )  # fmt: skip


def protocol_options(function):
    """How AP is computed (`dali eval`, `dali compare`): --recall-positions, --protocol,
    --front-only, --class, --min-gt-points (PROTOCOLS_HELP explains them in an epilog)."""
    return apply_options(function, [
        choice_option("--recall-positions", choices=["40", "11", "400"], default="40",
                      help="R40 (KITTI's) or R11 AP; 400: a fine recall grid, the same "
                           "computation without R40's 2-point steps (not a KITTI metric).",
                      tuning=True),
        choice_option("--protocol", choices=["auto", "kitti", "range", "st3d"], default="auto",
                      help="Difficulty filters (see below)."),
        tuning_option("--front-only", "front_only", is_flag=True,
                     help="Keep only ground truth and predictions centred in the front 90 deg "
                          "FOV and the detection range (x 0..70.4, |y| <= 40 m), as on KITTI's "
                          "FOV-cropped clouds; for 360-degree frames such as dali synth's."),
        tuning_option("--class", "class_name", default="Car", show_default=True,
                      help="Class to evaluate (dali's detectors find cars)."),
        tuning_option("--min-gt-points", type=click.IntRange(min=0), default=0, show_default=True,
                     help="Ignore ground-truth boxes with fewer points (needs num_points)."),
    ])  # fmt: skip
