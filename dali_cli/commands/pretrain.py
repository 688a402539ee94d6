"""`dali pretrain`: train the detector on a labeled source frame set."""

from __future__ import annotations

from pathlib import Path

import click

from dali_cli.commands.common import device_options, sensors_option, stage_options


def parse_floats(count: int):
    """A click callback turning 'a,b,c' into a tuple of `count` floats (None stays None)."""

    def callback(ctx, param, value):
        if value is None:
            return None
        try:
            numbers = tuple(float(v) for v in value.split(","))
        except ValueError:
            raise click.BadParameter(
                f"expected {count} comma-separated numbers, got '{value}'"
            ) from None
        if len(numbers) != count:
            raise click.BadParameter(f"expected {count} comma-separated numbers, got '{value}'")
        return numbers

    return callback


def training_options(function):
    """Budget, optimizer and input options shared by pretrain, retrain and self-train."""
    options = [
        click.option(
            "--epochs",
            type=click.FloatRange(min=0, min_open=True),
            default=10.0,
            show_default=True,
            help="Passes over the (source) training frames.",
        ),
        click.option(
            "--minutes",
            type=click.FloatRange(min=0, min_open=True),
            default=None,
            help="Wall-clock training budget instead of --epochs; the learning-rate "
            "schedule follows the elapsed fraction of the budget.",
        ),
        click.option(
            "--seed",
            type=int,
            default=0,
            show_default=True,
            help="Seed of initialization, sampling and augmentation.",
        ),
        click.option("--batch-size", type=click.IntRange(min=1), default=1, show_default=True),
        click.option(
            "--lr",
            type=click.FloatRange(min=0, min_open=True),
            default=5e-3,
            show_default=True,
            help="Peak learning rate of the one-cycle schedule (AdamW).",
        ),
        click.option(
            "--compile",
            "compile_net",
            is_flag=True,
            help="torch.compile the backbone and heads for training (~1 min cold start; "
            "pays off only where inductor beats eager convolutions, not on this project's "
            "AVX2 test machine).",
        ),
        click.option(
            "--threads",
            type=click.IntRange(min=1),
            default=None,
            help="torch threads per process (default: every core this process may use, divided "
            "by the processes torchrun starts on this machine; recorded in the manifest).",
        ),
        click.option(
            "--no-augment",
            "no_augment",
            is_flag=True,
            help="Disable gt-sampling, flip, rotation, scaling, object noise.",
        ),
        click.option("--quiet", is_flag=True, help="No progress bar."),
    ]
    for option in reversed(options):
        function = option(function)
    return device_options(function)


def read_json_option(path: str | None) -> dict | None:
    """The JSON document of an option's file (None without one); not JSON is a usage error."""
    import json

    if path is None:
        return None
    try:
        return json.loads(Path(path).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise click.BadParameter(f"{path}: not JSON ({error})") from None


@click.command(name="pretrain")
@click.option(
    "--source",
    type=click.Path(exists=True, file_okay=False),
    required=True,
    help="Labeled source: a FrameSet directory with boxes.parquet.",
)
@click.option(
    "--boxes",
    type=click.Path(exists=True),
    default=None,
    help="Labels to train on, if not SOURCE/boxes.parquet.",
)
@click.option(
    "--out",
    type=click.Path(file_okay=False),
    required=True,
    help="Checkpoint directory to write (e.g. RUN/iter0/model).",
)
@click.option(
    "--size-norm",
    type=click.Choice(["none", "sn", "ros"]),
    default="none",
    show_default=True,
    help="sn: shift source box sizes to the target mean (points scaled with them); "
    "ros: random object scaling U(--ros-range) per object, as augmentation.",
)
@click.option(
    "--target-profile",
    default=None,
    help="Sensor profile whose car_mean_lwh_m is the SN target (e.g. kitti).",
)
@click.option(
    "--target-size",
    default=None,
    callback=parse_floats(3),
    help="SN target mean size 'l,w,h' in m (overrides the profile).",
)
@click.option(
    "--ros-range",
    default="0.75,1.0",
    show_default=True,
    callback=parse_floats(2),
    help="ROS scale range 'lo,hi'.",
)
@click.option(
    "--features",
    type=click.Choice(["xyz", "xyzi"]),
    default="xyz",
    show_default=True,
    help="Point features fed to the pillar encoder.",
)
@click.option(
    "--detector-config",
    "config_overrides",
    type=click.Path(exists=True, dir_okay=False),
    default=None,
    callback=lambda _ctx, _param, path: read_json_option(path),
    help="JSON file of DetectorConfig fields to override (ranges, pillar size, widths; see docs/detector.md).",
)
@click.option(
    "--label",
    "labels",
    multiple=True,
    default=("Car",),
    show_default=True,
    help="Box labels to train on (repeatable).",
)
@training_options
@sensors_option
@stage_options
def command(source, boxes, out, size_norm, target_profile, target_size, ros_range, features,
            config_overrides, labels,
            epochs, minutes, seed, batch_size, lr, compile_net, threads, no_augment, quiet,
            device, precision, sensors_path, force, dry_run):  # fmt: skip
    """Train the CPU detector (pillars + CenterPoint heads + IoU score) on a labeled source.

    Reads SOURCE/frames.zarr and SOURCE/boxes.parquet (or --boxes). Writes OUT/model.pt (weights),
    OUT/model.json (config, provenance, metrics), OUT/train_log.parquet (step, loss terms, lr,
    frames/s) and OUT/manifest.json. An interrupted run keeps its state in OUT.resume/ and the
    same command resumes it. Training is deterministic for a given --seed and thread count.

    Distributed: `torchrun --nproc-per-node N $(which dali) pretrain ...` trains with
    DistributedDataParallel (gloo on the CPU, nccl on CUDA), --batch-size frames per process;
    rank 0 alone writes OUT. See docs/scale-out.md.
    """
    from stages.pretrain import run_pretrain

    outcome = run_pretrain(
        source, out, boxes=boxes, size_norm=size_norm, target_profile=target_profile,
        target_size=target_size, ros_range=ros_range, epochs=epochs, minutes=minutes, seed=seed,
        batch_size=batch_size, lr=lr, features=features, precision=precision, threads=threads,
        compile_net=compile_net, augment=not no_augment, labels=tuple(labels), config_overrides=config_overrides,
        sensors_path=sensors_path, force=force, dry_run=dry_run, progress=not quiet, device=device,
    )  # fmt: skip
    if outcome.status == "ran":
        train = (outcome.manifest or {}).get("outputs", {}).get("counts", {})
        click.echo(f"pretrain: {train.get('steps')} steps, {train.get('frames_seen')} frames seen")
