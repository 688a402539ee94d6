"""`dali pretrain`: train the detector on a labelled source frame set."""

from __future__ import annotations

import click

from dali_cli.commands.common import (
    choice_option,
    input_dir_option,
    out_dir_option,
    target_size_options,
    tuning_option,
)
from dali_cli.commands.detector_options import run_training_command, training_options
from dali_cli.commands.kinds import SCALE_PAIR


def read_json_option(value: str | None) -> dict | None:
    """The detector config overrides of `--detector-config` (None without it): an inline JSON
    object (text starting with "{") or the path of a JSON file; anything else, or bad JSON, is a
    usage error."""
    from pathlib import Path

    from dali_cli.runtime.errors import StageError
    from dali_cli.store.regular_files import parse_json_text, read_json_file

    if value is None:
        return None
    try:
        if value.lstrip().startswith("{"):
            document = parse_json_text(value, "--detector-config", "detector config")
        elif Path(value).is_file():
            document = read_json_file(value, "detector config")
        else:
            raise click.BadParameter(f"{value!r}: neither a JSON object nor a file")
    except (StageError, ValueError) as error:  # a FIFO, too large, not UTF-8, not JSON, too deep
        raise click.BadParameter(str(error)) from None
    if not isinstance(document, dict):
        raise click.BadParameter("detector config: not a JSON object")
    return document


@click.command(name="pretrain")
@input_dir_option("--source", help="Labelled source: a FrameSet directory with boxes.parquet.")
@click.option("--boxes", type=click.Path(exists=True), default=None,
              help="Labels to train on, if not SOURCE/boxes.parquet.")  # fmt: skip
@out_dir_option("Checkpoint directory to write (e.g. RUN/iter0/model).")
@choice_option("--size-norm", choices=["none", "sn", "ros"], default="none",
               help="sn: shift source box sizes to the target mean (points scaled with them); "
                    "ros: random object scaling U(--ros-range) per object, as augmentation.")  # fmt: skip
@target_size_options("Sensor profile whose car_mean_lwh_m is the SN target (e.g. kitti).",
                     "SN target mean size 'l,w,h' in m (overrides the profile).")  # fmt: skip
@tuning_option("--ros-range", type=SCALE_PAIR, default="0.75,1.0", show_default=True,
              help="ROS scale range 'lo,hi'.")  # fmt: skip
@choice_option("--features", choices=["xyz", "xyzi"], default="xyz", tuning=True,
               help="Point features fed to the pillar encoder.")  # fmt: skip
@tuning_option("--detector-config", "config_overrides",
              metavar="JSON|FILE", default=None,
              callback=lambda _ctx, _param, value: read_json_option(value),
              help="DetectorConfig fields to override, as a JSON object or a JSON file (ranges, "
                   "pillar size, widths, loss weights; see docs/detector.md).")  # fmt: skip
@click.option("--label", "labels", multiple=True, default=("Car",), show_default=True,
              help="Box labels to train on (repeatable).")  # fmt: skip
@training_options
def command(source, out, labels, **options):
    """Train the CPU detector (pillars + CenterPoint heads + IoU score) on a labelled source.

    Reads SOURCE/frames.zarr and SOURCE/boxes.parquet (or --boxes). Writes OUT/model.pt (weights),
    OUT/model.json (config, provenance, metrics), OUT/train_log.parquet (step, loss terms, lr,
    frames/s) and OUT/manifest.json. An interrupted run keeps its state in OUT.resume/ and the
    same command resumes it. Training is deterministic for a given --seed, thread count and CPU
    kernel path (the manifest's runtime records both); another CPU's rounding trains another
    model, as another seed would (docs/RESULTS.md, "Numerical stability").

    Distributed: `torchrun --nproc-per-node N $(which dali) pretrain ...` trains with
    DistributedDataParallel (gloo on the CPU, nccl on CUDA), --batch-size frames per process;
    rank 0 alone writes OUT. See docs/scale-out.md.
    """
    from stages.pretrain import run_pretrain

    run_training_command("pretrain", run_pretrain, source, out, labels=tuple(labels), **options)
