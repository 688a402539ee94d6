"""`dali pseudo-label`: pseudo-label the target at the PTSN scale ŝ."""

from __future__ import annotations

import click

from dali_cli.commands.common import (
    device_options,
    executor_options,
    model_target_out_options,
    sensors_option,
    stage_options,
    workers_option,
)


@click.command(name="pseudo-label")
@model_target_out_options("Trained model directory (model.pt + model.json).")
@click.option(
    "--scale-from",
    type=click.Path(exists=True),
    default=None,
    help="PTSN directory (or scale.json) of `dali ptsn-sweep`: its 'scale' is ŝ.",
)
@click.option(
    "--scale",
    type=click.FloatRange(0, min_open=True),
    default=None,
    help="Use this scale instead (overrides --scale-from's ŝ).",
)
@click.option(
    "--score-min",
    type=click.FloatRange(0, 1),
    default=0.3,
    show_default=True,
    help="Box score cut.",
)
@click.option(
    "--nms-iou",
    type=click.FloatRange(0, 1),
    default=0.1,
    show_default=True,
    help="BEV NMS IoU threshold after de-scaling.",
)
@click.option(
    "--target-profile", default=None, help="Target sensor profile (default: the frame set's)."
)
@click.option(
    "--mount-height-m",
    type=float,
    default=None,
    help="Target sensor height above ground for scaling (default: the target profile's).",
)
@click.option("--batch-size", type=click.IntRange(min=1), default=8, show_default=True)
@click.option(
    "--size-correction",
    "size_correction_method",
    type=click.Choice(["per-dim", "none"]),
    default="per-dim",
    show_default=True,
    help="per-dim: multiply l, w, h by E_est / mean pseudo-box size per dimension (bottom face "
    "kept), removing the bias one isotropic ŝ leaves; E_est from --scale-from's scale.json.",
)
@workers_option("1")
@executor_options
@click.option("--no-progress", is_flag=True, help="No progress bar.")
@device_options
@sensors_option
@stage_options
def command(model_dir, target_dir, out, sensors_path, no_progress, **options):
    """Pseudo-label the target: run the model on the target points scaled by ŝ about the ground,
    de-scale the boxes, keep score >= --score-min, BEV NMS at --nms-iou, then (by default)
    correct each dimension's remaining size bias against E_est (target statistics only).

    Reads MODEL, the TARGET frame set (never its labels) and --scale-from's scale.json.
    Writes OUT/boxes.parquet (one row per pseudo box: frame_id, x, y, z, l, w, h, yaw, score,
    label, num_points = original target points inside the box, scale = the scale used,
    size_factor_l/w/h = the correction factors),
    OUT/summary.json (boxes per frame, mean size vs E_est, score histogram) and manifest.json.
    """
    from stages.pseudo_label import pseudo_label

    pseudo_label(
        model_dir,
        target_dir,
        out,
        sensors_path=sensors_path,
        progress=not no_progress,
        **options,
    )
