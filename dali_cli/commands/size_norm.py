"""`dali size-norm`: a labelled frame set with its cars shifted to a model's size convention."""

from __future__ import annotations

import click

from dali_cli.commands.common import artifact_options, input_dir_option
from dali_cli.commands.kinds import SIZE_DELTA


@click.command(name="size-norm")
@input_dir_option("--data", "data", help="Labelled frame set (frames.zarr + boxes.parquet).")
@click.option("--like-model", type=click.Path(exists=True, file_okay=False), default=None,
              help="Shift by the SN delta this model's training applied to its source (a model "
                   "of `retrain --size-norm sn` or `pretrain --size-norm sn`).")  # fmt: skip
@click.option("--delta", "delta_lwh", type=SIZE_DELTA, default=None, metavar="DL,DW,DH",
              help="Shift every box's l, w, h by these metres instead (e.g. -0.76,-0.47,-0.22).")  # fmt: skip
@click.option("--label", "labels", multiple=True, default=("Car",), show_default=True,
              help="Box labels to shift (repeatable); other rows and their points stay.")  # fmt: skip
@artifact_options(progress=False)
def command(data, like_model, delta_lwh, labels, out, force, dry_run):
    """Write DATA with every box of --label resized by a fixed l, w, h delta (bottom centre and
    yaw kept) and the points inside it moved with it: the view of the source that a model
    trained with a size shift (SN) learned from.

    Use it for the forgetting check of such a model: `dali retrain --size-norm sn` teaches
    target-sized cars, so on the raw source validation set its boxes miss IoU 0.7 by design;
    `dali size-norm --data SOURCE_VAL --like-model MODEL --out DIR` then `dali eval --model MODEL
    --data DIR --scale 1` measures what it still knows of the source. Writes OUT/frames.zarr,
    OUT/boxes.parquet (all input rows; shifted boxes' z, l, w, h replaced) and OUT/manifest.json.
    A box the shift would leave without a positive size is an error naming its frame and row.
    """
    from stages.size_norm import size_norm

    size_norm(
        data, out, delta_lwh=delta_lwh, like_model=like_model, labels=tuple(labels),
        force=force, dry_run=dry_run,
    )  # fmt: skip
