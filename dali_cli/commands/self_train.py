"""`dali self-train`: fine-tune the final model on the target with its own pseudo labels."""

from __future__ import annotations

import click

from dali_cli.commands.common import data_option, input_dir_option, out_dir_option
from dali_cli.commands.detector_options import run_training_command, training_options
from dali_cli.commands.kinds import SCALE


@click.command(name="self-train")
@input_dir_option("--init", help="Model to fine-tune (e.g. RUN/iter2/model, the final DALI model).")
@data_option("target",
             help="Target FrameSet directory (its frames only; its labels are never read).")  # fmt: skip
@input_dir_option("--pseudo",
                  help="Pseudo labels of INIT on DATA from `dali pseudo-label` (e.g. "
                       "RUN/iter3/pseudo).")  # fmt: skip
@out_dir_option("Checkpoint directory to write.")
@click.option("--scale", type=SCALE, default=None,
              help="Train in the frame scaled by this s (default: the pseudo labels' own PTSN "
                   "scale ŝ).")  # fmt: skip
@input_dir_option("--pseudo-from", required=False,
                  help="The frame set PSEUDO was made from when it is not DATA: the same scans at "
                       "more beams (DATA imported from them with --beams), so that a dense "
                       "LiDAR's model labels a sparse one's frames. Every pseudo box's frame "
                       "must be one of DATA's.")  # fmt: skip
@training_options
def command(init, target, pseudo, out, **options):
    """Self-training (the paper's ‡): fine-tune INIT on the raw DATA frames with its own pseudo
    labels, both scaled by ŝ about the ground, as the model sees the target at test time.

    Reads INIT/model.pt + model.json, DATA/frames.zarr and PSEUDO/boxes.parquet (never
    DATA/boxes.parquet). An epoch is one pass over the target frames. Writes OUT/model.pt,
    model.json, train_log.parquet and manifest.json (as pretrain); evaluate with
    `dali eval --scale-from` the sweep that made PSEUDO.
    """
    from stages.self_train import run_self_train

    run_training_command(
        "self-train", run_self_train, init, target, pseudo, out,
        extra=", {pseudo_boxes} pseudo boxes", **options,
    )  # fmt: skip
