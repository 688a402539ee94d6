"""`dali pseudo-label`: pseudo-label the target at the PTSN scale ŝ."""

from __future__ import annotations

import click

from dali_cli.commands.common import (
    choice_option,
    executor_options,
    finite_range,
    model_target_out_options,
    scale_from_option,
    tuning_option,
    workers_option,
)
from dali_cli.commands.detector_options import (
    score_min_option,
    target_profile_option,
    target_scaling_options,
)
from dali_cli.commands.kinds import SCALE


@click.command(name="pseudo-label")
@model_target_out_options("Trained model directory (model.pt + model.json).")
@scale_from_option()
@click.option("--scale", type=SCALE, default=None,
              help="Use this scale instead (overrides --scale-from's ŝ).")  # fmt: skip
@score_min_option()
@tuning_option("--nms-iou", type=finite_range(0, 1), default=0.1, show_default=True,
              help="BEV NMS IoU threshold after de-scaling.")  # fmt: skip
@target_profile_option()
@choice_option("--size-correction", "size_correction_method", choices=["per-dim", "none"], tuning=True,
               default="per-dim",
               help="per-dim: multiply l, w, h by E_est / mean pseudo-box size per dimension "
                    "(bottom face kept), removing the bias one isotropic ŝ leaves; E_est from "
                    "--scale-from's scale.json.")  # fmt: skip
@tuning_option("--fit-points/--no-fit-points", default=True, show_default=True,
              help="Move and turn each pseudo box (its size kept) so its sides hug the target "
                   "points it holds: shifts up to 1 m along the car and 0.2 m across, turns "
                   "up to 8 degrees (dali_cli.labels.box_fit). Target points only, no label "
                   "(docs/ppcg.md).")  # fmt: skip
@workers_option("1")
@executor_options
@target_scaling_options
def command(model_dir, target_dir, out, sensors_path, no_progress, fit_points, **options):
    """Pseudo-label the target: run the model on the target points scaled by ŝ about the ground,
    de-scale the boxes, keep score >= --score-min, BEV NMS, then correct each dimension's
    remaining size bias against E_est (target statistics only) and move each box onto its
    points (the NMS threshold, the correction and the fit are tuning options: --nms-iou,
    --size-correction, --no-fit-points, shown below).

    Reads MODEL, the DATA frame set (never its labels) and --scale-from's scale.json.
    Writes OUT/boxes.parquet (one row per pseudo box: frame_id, x, y, z, l, w, h, yaw, score,
    label, num_points = original target points inside the box, size_factor_l/w/h = the
    correction factors), OUT/scale.json (the scale used: --scale-from's scale.json with
    scale_source and the pivot mount_height_m; the one record of ŝ in the output),
    OUT/summary.json (boxes per frame, mean size vs E_est, score histogram) and manifest.json.
    """
    from dali_cli.labels.box_fit import PointFit
    from stages.pseudo_label import pseudo_label

    pseudo_label(
        model_dir,
        target_dir,
        out,
        sensors_path=sensors_path,
        progress=not no_progress,
        point_fit=PointFit() if fit_points else None,
        **options,
    )
