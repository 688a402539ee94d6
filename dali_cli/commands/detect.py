"""`dali detect`: a trained model's boxes on one's own scans (stages/detect.py)."""

from __future__ import annotations

from pathlib import Path

import click

from dali_cli.commands.common import (
    BATCH,
    artifact_options,
    ran_counts,
    scale_from_option,
    sensors_option,
    tuning_option,
)
from dali_cli.commands.detector_options import device_options, score_min_option
from dali_cli.commands.kinds import SCALE, VIEW_DEG
from dali_cli.commands.protocol_options import calib_option


@click.command(name="detect")
@click.argument("scans", type=click.Path(exists=True, path_type=Path))
@click.option("--model", type=click.Path(exists=True, file_okay=False, path_type=Path),
              required=True, help="Model directory (model.pt, model.json; e.g. models/kitti-hdl64e).")  # fmt: skip
@click.option("--scale", type=SCALE, default=None,
              help="PTSN scale to run at. Default: MODEL/scale.json when there, else 1.")  # fmt: skip
@scale_from_option(tuning=True)
@click.option("--sensor", default=None,
              help="Sensor profile of the scans (sensors.toml; its mount height sets the ground). "
                   "Default: kitti for .bin, nuscenes for .pcd.bin, a frame set's own; else the "
                   "sensor the model is for (model.json's config: its target's once adapted).")  # fmt: skip
@calib_option(
    "With it OUT/label_2 holds camera-frame label_2 files of the boxes inside the image. "
    "Default: a KITTI raw drive's or object split's own."
)
@click.option("--front-deg", type=VIEW_DEG, metavar="DEG", default=None,
              help="Keep only the points within this many degrees of azimuth about the sensor's "
                   "+x (360: every point). Default: the front view the model was adapted on "
                   "(model.json's config front_deg: 82, KITTI's camera view, for "
                   "models/kitti-hdl64e), else every point.")  # fmt: skip
@score_min_option(help="Write only boxes scored at least this.")
@click.option("--rerun", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write a Rerun recording (.rrd) of the scans and their boxes coloured by "
                   "score (rerun-sdk).")  # fmt: skip
@tuning_option("--batch-size", type=BATCH, default=4, show_default=True,
              help="Scans per network pass.")  # fmt: skip
@device_options
@sensors_option
@artifact_options()
def command(scans, model, scale, scale_from, sensor, calib, front_deg, score_min, rerun,
            batch_size, out, device, precision, sensors_path, no_progress, force, dry_run):  # fmt: skip
    """Detect cars in SCANS with MODEL and write OUT.

    SCANS: a scan file or a folder of them (KITTI .bin, PCD ascii or binary, nuScenes .pcd.bin,
    .npy of (n, >=3)), a KITTI raw drive (velodyne_points/data), a KITTI object split (velodyne/)
    or a dali frame set. OUT/boxes.parquet holds every box (LiDAR frame, score, points inside);
    OUT/label_2/<frame>.txt KITTI label_2 lines (camera frame, with --calib or the data's own
    calib) of the boxes inside the image, those outside left out and counted in the summary line;
    else OUT/lidar/<frame>.txt lines 'x y z l w h yaw Car score' (metres, radians, LiDAR frame).
    The boxes are the model's own, at the model's test-time scale, on the scans cropped to the
    model's front view (--front-deg): what `dali eval` scores. Written atomically with a
    manifest; rerun only when an input or option changed.
    """
    from stages.detect import run_detect

    outcome = run_detect(
        model=model, scans=scans, out=out, scale=scale, scale_from=scale_from, sensor=sensor,
        calib=calib, score_min=score_min, front_deg=front_deg, batch_size=batch_size,
        device=device, precision=precision, progress=not no_progress, force=force,
        dry_run=dry_run, sensors_path=sensors_path, rerun=rerun,
    )  # fmt: skip
    if (counts := ran_counts(outcome)) is not None:
        label_2 = (
            f" ({counts['boxes_written']} written to label_2, {counts['boxes_outside_image']} "
            "outside the image left out)"
            if "boxes_written" in counts
            else ""
        )
        click.echo(
            f"  {counts['boxes']} boxes in {counts['frames']} scans{label_2}, "
            f"{counts['frames_per_s']} frames/s ({counts['seconds']} s)"
        )
