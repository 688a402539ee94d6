"""`dali ptsn-sweep`: find the PTSN scale ŝ of a trained model on an unlabelled target."""

from __future__ import annotations

import click

from dali_cli.commands.common import (
    SEED,
    choice_option,
    finite_range,
    model_target_out_options,
    renamed_option,
    tuning_option,
)
from dali_cli.commands.detector_options import (
    score_min_option,
    target_profile_option,
    target_scaling_options,
)
from dali_cli.commands.kinds import TOLERANCE
from dali_cli.ptsn import FRAME_CAP, ScaleRange, parse_scale_range


class ScaleRangeType(click.ParamType):
    """LOW:HIGH[:STEP] → ScaleRange; a bad spec is a usage error (exit 2)."""

    name = "LOW:HIGH[:STEP]"

    def convert(self, value, param, ctx):
        if isinstance(value, ScaleRange):
            return value
        try:
            return parse_scale_range(value)
        except ValueError as error:
            self.fail(str(error), param, ctx)


SCALE_RANGE = ScaleRangeType()


@click.command(name="ptsn-sweep")
@model_target_out_options("Trained model directory (model.pt + model.json), e.g. RUN/iter0/model.")
@tuning_option("--scales", "scale_range", type=SCALE_RANGE, default="0.8:1.4", show_default=True,
              help="Swept scales LOW:HIGH[:STEP] (STEP default 0.01; the grid and the confirm "
                   "resolution).")  # fmt: skip
@renamed_option("--target-size", "--expected-size", "expected_size", default="sn",
                show_default=True,
                help="E_est, the target's expected mean car size: 'sn' (the target profile's "
                     "car_mean_lwh_m, sensors.toml), 'ros' (source mean x mean ROS factor) or "
                     "L,W,H in metres.")  # fmt: skip
@choice_option("--search", choices=["bracket", "grid"], tuning=True, default="bracket",
               help="bracket: secant on a frame subsample, confirmed on all frames; grid: every "
                    "scale.")  # fmt: skip
@tuning_option("--frames", type=click.IntRange(min=1), default=None,
               help=f"Sweep on N frames, evenly spread over the target (one drawn, seeded, from "
                    f"each of N equal runs of frames). Default: {FRAME_CAP} (every frame of a "
                    f"smaller target): on six real drives and their 514 frames ŝ within 0.0013 of the "
                    f"sweep of every frame (docs/ptsn.md).")  # fmt: skip
@tuning_option("--frame-fraction", type=finite_range(0, 1, min_open=True), default=None,
              help="Sweep on this fraction of the frames instead, evenly spread (seeded); 1: "
                   "every frame.")  # fmt: skip
@score_min_option()
@choice_option("--no-detections", choices=["identity", "error"], tuning=True, default="identity",
               help="When no box reaches --score-min at any tried scale: identity = write ŝ = 1 "
                    "(no size normalization) with a warning recorded in scale.json and the "
                    "manifest; error = exit 1.")  # fmt: skip
@choice_option("--mean", choices=["per-frame", "pooled"], tuning=True, default="per-frame",
               help="per-frame: mean of per-frame means (paper Eq. 1); pooled: one mean over all "
                    "boxes.")  # fmt: skip
@choice_option("--match", choices=["volume", "lwh"], tuning=True, default="volume",
               help="Match mean volume (a 1-D root) or l, w, h in the least-squares sense.")  # fmt: skip
@click.option("--seed", type=SEED, default=0, show_default=True,
              help="Seed of the frame subsamples.")  # fmt: skip
@tuning_option("--subsample-fraction", type=finite_range(0, 1, min_open=True), default=0.25,
              show_default=True, help="bracket: fraction of the frames used for the secant phase.")  # fmt: skip
@tuning_option("--subsample-min", type=click.IntRange(min=1), default=16, show_default=True,
              help="bracket: at least this many frames in the secant phase.")  # fmt: skip
@tuning_option("--noise", type=TOLERANCE, default=0.02, show_default=True,
              help="How far the criterion may rise with s and still count as monotone (volume: "
                   "log ratio).")  # fmt: skip
@target_profile_option()
@click.option("--plot", is_flag=True, help="Also write sweep.png (mean volume vs scale).")
@target_scaling_options
def command(model_dir, target_dir, out, scale_range, sensors_path, no_progress, **options):
    """Find the PTSN scale ŝ: the point-cloud scale at which the model's mean predicted car size
    E_pred(s) (boxes de-scaled, score >= --score-min) matches the expected target size E_est.

    Reads MODEL (model.json, model.pt) and the DATA frame set only: never target labels.
    Writes OUT/scale.json ("scale": ŝ, E_est, E_pred at ŝ, per-dimension bias, passes, detector
    frames, strategy, clipping), OUT/sweep.parquet (one row per evaluated scale and frame set:
    frames, boxes, mean l/w/h, mean volume, seconds), OUT/detections.parquet (every box at the
    scales evaluated on all frames: scale, frame, l, w, h, score), OUT/sweep.png with --plot, and manifest.json.
    When E_est lies outside --scales, ŝ is clipped to the bound and a warning says so. When the
    model finds no box with score >= --score-min at any tried scale (an undertrained model),
    ŝ = 1 with fallback "no-detections" and a warning (or exit 1 with --no-detections error).
    """
    from stages.ptsn_sweep import ptsn_sweep

    ptsn_sweep(
        model_dir,
        target_dir,
        out,
        scale_range=scale_range,
        sensors_path=sensors_path,
        progress=not no_progress,
        **options,
    )
