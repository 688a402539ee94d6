"""`dali ppcg-rc`: ray-constrained pseudo point clouds of the target (stage 4)."""

from __future__ import annotations

import click

from dali_cli.commands.common import (
    SEED,
    apply_options,
    data_option,
    executor_options,
    input_dir_option,
    no_progress_option,
    out_dir_option,
    sensors_option,
    stage_options,
    tuning_option,
    workers_option,
)
from dali_cli.commands.detector_options import target_profile_option
from dali_cli.commands.kinds import MARGIN_M
from dali_cli.ppcg.frame import DEFAULT_POINT_MARGIN_M
from dali_cli.world.cars import LABEL_SLACK_M


def ppcg_options(function):
    """Options shared by ppcg-rc and ppcg-cf."""
    decorators = [
        data_option("target_dir", help="Target frame set (frames.zarr)."),
        click.option("--boxes", "boxes_dir", required=True, type=click.Path(exists=True),
                     help="Box table directory (boxes.parquet): pseudo labels, or labels for "
                          "controlled runs."),
        input_dir_option("--library", "library_dir", help="Model library of `dali library build`."),
        out_dir_option(),
        target_profile_option("sensor"),
        tuning_option("--models", type=click.Choice(["cad", "points"]), default=None,
                     help="Model kind to fit  [default: cad if the library has meshes, else points]"),
        tuning_option("--top-k", type=click.IntRange(min=1), default=1, show_default=True,
                     help="Pick at random among the K best models (per-box seed); 1 = the best."),
        click.option("--seed", type=SEED, default=0, show_default=True, help="Run seed."),
        tuning_option("--ground-margin-m", type=MARGIN_M, default=0.1,
                     show_default=True,
                     help="Points of a box below max(box bottom, -mount height) + this are "
                          "ground: kept."),
        tuning_option("--orient-models/--no-orient-models", default=None,
                     help="Turn a box round when its car model fits the box's points better "
                          "facing the other way (dali_cli.ppcg.orient; for pseudo labels of a "
                          "model without a direction head, whose headings are axes). Mesh "
                          "models only  [default: on with mesh models, off with point models]"),
        tuning_option("--point-margin-m", type=MARGIN_M,
                     default=DEFAULT_POINT_MARGIN_M, show_default=True,
                     help="A box's points are those in the box grown by this on every side: "
                          "LiDAR points lie on a car's surface, so a pseudo box a little off "
                          "leaves part of the car outside it as raw points beside the model "
                          "(0: the points in the box, as the paper)."),
        tuning_option("--label-slack-m", type=MARGIN_M, nargs=3,
                     default=tuple(float(v) for v in LABEL_SLACK_M), show_default=True,
                     help="L W H: room a box leaves around its car, as the source's labels "
                          "draw it (metres off each end, each side, the top); the model fills "
                          "the box shrunk by it. The default is the synthetic world's labels "
                          "(dali synth); 0 0 0 fills the whole box, as the paper."),
        click.option("--label", default="Car", show_default=True,
                     help="Process boxes of this label; other rows pass through as 'raw'."),
        workers_option("1"),
        no_progress_option,
    ]  # fmt: skip
    function = executor_options(function)
    return apply_options(function, decorators)


@click.command(name="ppcg-rc")
@ppcg_options
@tuning_option("--max-points", type=click.IntRange(min=2), default=300, show_default=True,
              help="Boxes with this many points or more are dense: skipped.")  # fmt: skip
@tuning_option("--min-points", type=click.IntRange(min=1), default=3, show_default=True,
              help="Boxes with fewer points are skipped; fewer hits keep the raw points.")  # fmt: skip
@sensors_option
@stage_options
def command(target_dir, boxes_dir, library_dir, out, no_progress, **options):
    """Ray-constrained PPCG: for each box with MIN <= points < MAX (points above its ground
    height), fit the best library model (anisotropic scale into the box), cast the rays
    sensor -> each point against it and move the point to the first hit (point models: the
    nearest model point within 2 x 360/points-per-beam degrees of the ray). Misses are dropped;
    ground points stay; RC never adds points.

    Reads DATA, the BOXES table and the LIBRARY. Writes OUT/frames.zarr (every target frame,
    processed boxes' points replaced), OUT/boxes.parquet (the input rows plus ppcg = rc|raw,
    ppcg_reason, points_before, points_after, model_id) and OUT/manifest.json (counts of
    boxes processed and skipped, per-frame timing).
    """
    from stages.ppcg_rc import ppcg_rc

    ppcg_rc(target_dir, boxes_dir, library_dir, out, progress=not no_progress, **options)
