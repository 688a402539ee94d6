"""`dali compare`: AP of several prediction tables on the same frames with a paired bootstrap."""

from __future__ import annotations

from pathlib import Path

import click

from dali_cli.commands.common import FRACTION, SEED, no_progress_option, tuning_option
from dali_cli.commands.protocol_options import PROTOCOLS_HELP, protocol_options

EPILOG = (
    """\b
Rows (--pred NAME=PATH, two or more; the first is the reference): box tables (a directory with
boxes.parquet, a .parquet file such as an eval's predictions.parquet) or KITTI label_2-style
directories, all predicted on the frames of --gt. Each row is evaluated on all frames, then on
--samples draws of the frames with replacement, the same draws for every row (paired). A frame is
the unit drawn (its boxes are not independent); a frame drawn twice counts twice.

\b
What it answers: how much of a row's AP, and of its difference to the reference, is the choice
of evaluation frames. It does not see the training's chance (seeds): `dali report` over seeds
gives that. At 200 validation frames AP_3D@0.7 moves in steps (a 3 mm change of every box's
height moved one row by 1.4: docs/evaluation.md).

"""
    + PROTOCOLS_HELP
    + """
\b
Output: per metric ("3d all", "bev 0-30", ...; kitti: easy/moderate/hard) each row's AP on all
frames ± its bootstrap std, and for every row after the first Δ = AP(row) - AP(reference) on all
frames ± the bootstrap std of Δ, its 2.5-97.5 % interval and P(Δ<=0), the share of draws where
the row does not beat the reference. --out FILE.json writes it ({"bootstrap": {"reference",
"frames", "samples", "seed", "rows": {NAME: {METRIC: {"ap", "std", "delta", "delta_std",
"delta_interval_95", "share_not_above_reference"}}}}, "settings", "inputs"}).
"""
)


@click.command(name="compare", epilog=EPILOG)
@click.option("--pred", "preds", multiple=True, required=True, metavar="NAME=PATH",
              help="A row: its name and its predictions; repeat (the first is the "
                   "reference). The name ends at the first '=', so it cannot hold one.")  # fmt: skip
@click.option("--gt", "gt_path", required=True, type=click.Path(exists=True, path_type=Path),
              help="Ground truth (box table or label_2 dir) of the frames.")  # fmt: skip
@click.option("--iou", type=FRACTION, default=0.7, show_default=True,
              help="IoU threshold (a match needs IoU > this).")  # fmt: skip
@protocol_options
@tuning_option("--samples", type=click.IntRange(min=2), default=1000, show_default=True,
              help="Bootstrap draws (about 0.1 s each per row on 200 frames).")  # fmt: skip
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the draws.")
@click.option("--out", type=click.Path(path_type=Path),
              help="Also write the comparison to this .json file (atomically).")  # fmt: skip
@no_progress_option
def command(preds, gt_path, iou, recall_positions, protocol, front_only, class_name,
            min_gt_points, samples, seed, out, no_progress):  # fmt: skip
    """AP of several prediction tables on the same frames, and how much of each difference is
    the choice of frames (a paired bootstrap over the frames)."""
    from dali_cli.evaluation.evaluate import Protocol
    from stages.compare import format_comparison, run_compare

    settings = Protocol(
        iou=iou, recall_positions=int(recall_positions), protocol=protocol,
        class_name=class_name, min_gt_points=min_gt_points, front_only=front_only,
    )  # fmt: skip
    document = run_compare(
        preds=preds, gt_path=gt_path, settings=settings, samples=samples, seed=seed, out=out,
        progress=not no_progress,
    )  # fmt: skip
    click.echo(format_comparison(document))
    if out is not None:
        click.echo(f"wrote {out}")
