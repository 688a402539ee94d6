"""`dali pseudo-label`: pseudo-label the target at the PTSN scale ŝ."""

from __future__ import annotations

import click

from dali_cli.commands.common import (
    choice_option,
    executor_options,
    model_target_out_options,
    score_min_option,
    target_profile_option,
    target_scaling_options,
    workers_option,
)
from dali_cli.labels import tta


def parse_scale_factors(ctx, param, value: str) -> tuple[float, ...]:
    """'0.9,1,1.1' -> (0.9, 1.0, 1.1), checked by tta.Views (positive, distinct)."""
    try:
        factors = tuple(float(v) for v in value.split(","))
        tta.Views(factors)
    except ValueError as error:
        raise click.BadParameter(f"'{value}': {error}") from None
    return factors


def views_of(on: bool, factors: tuple[float, ...], mirror: bool):
    """The stage's test-time views (None: off). --tta-scales or --tta-mirror without --tta is a
    usage error rather than silently ignored."""
    from click.core import ParameterSource

    from dali_cli.labels import tta as augmentation

    if not on:
        context = click.get_current_context()
        for name, flag in (("tta_scales", "--tta-scales"), ("tta_mirror", "--tta-mirror")):
            if context.get_parameter_source(name) is not ParameterSource.DEFAULT:
                raise click.UsageError(f"{flag} needs --tta")
        return None
    return augmentation.Views(factors, mirror)


@click.command(name="pseudo-label")
@model_target_out_options("Trained model directory (model.pt + model.json).")
@click.option("--scale-from", type=click.Path(exists=True), default=None,
              help="PTSN directory (or scale.json) of `dali ptsn-sweep`: its 'scale' is ŝ.")  # fmt: skip
@click.option("--scale", type=click.FloatRange(0, min_open=True), default=None,
              help="Use this scale instead (overrides --scale-from's ŝ).")  # fmt: skip
@score_min_option
@click.option("--nms-iou", type=click.FloatRange(0, 1), default=0.1, show_default=True,
              help="BEV NMS IoU threshold after de-scaling.")  # fmt: skip
@target_profile_option
@choice_option("--size-correction", "size_correction_method", choices=["per-dim", "none"],
               default="per-dim",
               help="per-dim: multiply l, w, h by E_est / mean pseudo-box size per dimension "
                    "(bottom face kept), removing the bias one isotropic ŝ leaves; E_est from "
                    "--scale-from's scale.json.")  # fmt: skip
@click.option("--tta/--no-tta", default=False, show_default=True,
              help="Test-time augmentation: label each frame in several views (ŝ times each "
                   "--tta-scales factor, each also mirrored left-right) and fuse the boxes the "
                   "views agree on (score-weighted mean; score = sum over views / views): "
                   "fewer false and better placed boxes, at one detector pass per view. Off by "
                   "default: the better labels did not make a better retrained model "
                   "(docs/RESULTS.md, session 12).")  # fmt: skip
@click.option("--tta-scales", default=",".join(f"{f:g}" for f in tta.DEFAULT_SCALE_FACTORS),
              show_default=True, callback=parse_scale_factors,
              help="Comma-separated factors of ŝ, one view each (with --tta).")  # fmt: skip
@click.option("--tta-mirror/--no-tta-mirror", default=True, show_default=True,
              help="Also label each view mirrored left-right (with --tta).")  # fmt: skip
@click.option("--fit-points/--no-fit-points", default=True, show_default=True,
              help="Move and turn each pseudo box (its size kept) so its sides hug the target "
                   "points it holds: shifts up to 1 m along the car and 0.2 m across, turns "
                   "up to 8 degrees (dali_cli.labels.box_fit). Target points only, no label. Matched "
                   "boxes at 3D IoU >= 0.7: 0.48-0.57 -> 0.67-0.71 (docs/results/history.md).")  # fmt: skip
@click.option("--fit-ground/--no-fit-ground", default=False, show_default=True,
              help="Then put each box's bottom on the ground the target points show around it "
                   "(a robust plane or level fit to the free points within 10 m of the box; "
                   "x, y, size and yaw kept; dali_cli.labels.ground_fit). Target points only, no "
                   "label. Off by default: better heights (0.838 -> 0.859 of the matched boxes "
                   "at 3D IoU >= 0.7), the same retrained model (docs/RESULTS.md, session 29).")  # fmt: skip
@click.option("--ignore-min", type=click.FloatRange(0, 1), default=None,
              help="Also write the boxes scored in [--ignore-min, --score-min), as detected, "
                   "labelled DontCare: ignore regions for `dali retrain --ignore-label "
                   "DontCare` (neither car nor background there). PPCG passes them through "
                   "untouched. Off by default: with --score-min 0.6 --ignore-min 0.3 the 1:7 "
                   "retraining gained +0.39 +- 0.29 AP_3D, but --score-min 0.6 alone as much; "
                   "1:1 level (docs/RESULTS.md, session 30; over seeds 0-2 the cut alone is +0.26 "
                   "+- 0.16, session 31).")  # fmt: skip
@workers_option("1")
@executor_options
@target_scaling_options
def command(model_dir, target_dir, out, sensors_path, no_progress, tta, tta_scales, tta_mirror,
            fit_points, fit_ground, **options):  # fmt: skip
    """Pseudo-label the target: run the model on the target points scaled by ŝ about the ground
    (with --tta in ten views fused box by box), de-scale the boxes, keep score >=
    --score-min, BEV NMS at --nms-iou, then (by default)
    correct each dimension's remaining size bias against E_est (target statistics only),
    and (by default, --fit-points) move each box onto its points (with --fit-ground, then put
    its bottom on the ground around it).

    Reads MODEL, the TARGET frame set (never its labels) and --scale-from's scale.json.
    Writes OUT/boxes.parquet (one row per pseudo box: frame_id, x, y, z, l, w, h, yaw, score,
    label, num_points = original target points inside the box, size_factor_l/w/h = the
    correction factors), OUT/scale.json (the scale used: --scale-from's scale.json with
    scale_source and the pivot mount_height_m; the one record of ŝ in the output),
    OUT/summary.json (boxes per frame, mean size vs E_est, score histogram) and manifest.json.
    """
    from dali_cli.labels.box_fit import PointFit
    from dali_cli.labels.ground_fit import GroundFit
    from stages.pseudo_label import pseudo_label

    pseudo_label(
        model_dir,
        target_dir,
        out,
        sensors_path=sensors_path,
        progress=not no_progress,
        views=views_of(tta, tta_scales, tta_mirror),
        point_fit=PointFit() if fit_points else None,
        ground_fit=GroundFit() if fit_ground else None,
        **options,
    )
