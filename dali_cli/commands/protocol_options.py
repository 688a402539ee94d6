"""How `dali eval`, `dali compare` and `dali detect` read labels and compute AP: the protocol
options (--protocol, --recall-positions, --front-only, --class, --min-gt-points), their epilog,
and --calib."""

from __future__ import annotations

from pathlib import Path

import click

from dali_cli.commands.common import apply_options, choice_option, tuning_option

PROTOCOLS_HELP = """\b
Protocols: kitti = easy/moderate/hard from the KITTI label fields (2D box height, occlusion,
truncation); range = all boxes and BEV-distance bands 0-30, 30-50, 50-80 m; st3d = ST3D's
target-domain evaluation (ground truth only in the front 90 deg FOV and the detection range,
every box 'easy'); auto (default) = kitti when the ground truth has the KITTI fields, else range.
dali synth labels carry the KITTI fields (2D box, truncation, occlusion level of a virtual KITTI
camera at the sensor), so --protocol kitti gives easy/moderate/hard on synthetic data too.
Van ground truths are ignored for Car. Of the tuning options (shown above): --front-only
restricts any protocol to that front region, ground truth and predictions alike (KITTI's clouds
are FOV-cropped; dali synth's are 360 degrees); --min-gt-points marks ground-truth cars with
fewer points as ignored (neither miss nor false positive), it never drops them;
--recall-positions 400 reads the precision at exact recalls (sets of fewer than 41 cars).
"""


def calib_option(help: str):
    """--calib: KITTI camera calibration (importers/calibration.py: a calib .txt for every
    frame, a raw drive's date folder, or a folder of <frame>.txt), a Path or None."""
    return click.option(
        "--calib", type=click.Path(exists=True, path_type=Path), default=None,
        help="KITTI calibration: a calib .txt for every frame, a folder of <frame>.txt, or a raw "
             "drive's date folder (holding calib_cam_to_cam.txt, calib_velo_to_cam.txt). " + help,
    )  # fmt: skip


def protocol_options(function):
    """How AP is computed (`dali eval`, `dali compare`): --recall-positions, --protocol,
    --front-only, --class, --min-gt-points (PROTOCOLS_HELP explains them in an epilog)."""
    return apply_options(function, [
        choice_option("--recall-positions", choices=["40", "11", "400"], default="40",
                      help="R40 (KITTI's) or R11 AP; 400: a fine recall grid, the same "
                           "computation without R40's 2-point steps (not a KITTI metric).",
                      tuning=True),
        choice_option("--protocol", choices=["auto", "kitti", "range", "st3d"], default="auto",
                      help="Difficulty filters (see below)."),
        tuning_option("--front-only", "front_only", is_flag=True,
                     help="Keep only ground truth and predictions centred in the front 90 deg "
                          "FOV and the detection range (x 0..70.4, |y| <= 40 m), as on KITTI's "
                          "FOV-cropped clouds; for 360-degree frames such as dali synth's."),
        tuning_option("--class", "class_name", default="Car", show_default=True,
                      help="Class to evaluate (dali's detectors find cars)."),
        tuning_option("--min-gt-points", type=click.IntRange(min=0), default=0, show_default=True,
                     help="Ignore ground-truth boxes with fewer points (needs num_points)."),
    ])  # fmt: skip
