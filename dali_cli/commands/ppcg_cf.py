"""`dali ppcg-cf`: constraint-free pseudo point clouds of the target (stage 5)."""

from __future__ import annotations

import click

from dali_cli.commands.common import sensors_option, stage_options, tuning_option
from dali_cli.commands.kinds import DISTANCE_RANGE
from dali_cli.commands.ppcg_rc import ppcg_options


@click.command(name="ppcg-cf")
@ppcg_options
@tuning_option("--range-m", type=DISTANCE_RANGE, default="20:50", show_default=True,
              help="LOW:HIGH: each box is moved radially to a range drawn uniformly from it (m).")  # fmt: skip
@sensors_option
@stage_options
def command(target_dir, boxes_dir, library_dir, out, no_progress, range_m, **options):
    """Constraint-free PPCG: for each box, fit the best library model, move the box radially to
    a range drawn per box from --range-m (heading kept), scan it with the target sensor's rays
    inside the box's angular window, move the first hits back and replace the box's points
    (ground points stay). Random draws come from (seed, frame, box): any --workers gives the
    same output.

    Reads DATA, the BOXES table and the LIBRARY. Writes OUT/frames.zarr, OUT/boxes.parquet
    (input rows plus ppcg = cf|raw, ppcg_reason, points_before, points_after, model_id) and
    OUT/manifest.json (counts, per-frame timing).
    """
    from stages.ppcg_cf import ppcg_cf

    ppcg_cf(
        target_dir,
        boxes_dir,
        library_dir,
        out,
        range_m=range_m,
        progress=not no_progress,
        **options,
    )
