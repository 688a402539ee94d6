"""`dali synth`: a synthetic labelled domain (FrameSet + boxes.parquet) from a sensor and a car-size profile."""

from __future__ import annotations

import click

from dali_cli.commands.common import (
    BATCH,
    SEED,
    artifact_options,
    executor_options,
    ran_counts,
    sensors_option,
    tuning_option,
    workers_option,
)


@click.command(name="synth")
@click.option("--sensor", required=True,
              help="Sensor profile of sensors.toml that scans the scenes (kitti, waymo, "
                   "nuscenes, ...).")  # fmt: skip
@click.option("--cars", "cars_profile", default=None,
              help="Profile whose car_mean_lwh_m / car_std_lwh_m size the cars. Default: "
                   "--sensor.")  # fmt: skip
@click.option("--frames", type=click.IntRange(min=1), required=True, help="Number of frames.")
@click.option("--seed", type=SEED, default=0, show_default=True,
              help="Run seed; frame k depends only on (seed, k).")  # fmt: skip
@workers_option("the cores available")
@executor_options
@tuning_option("--threads", type=BATCH, default=1, show_default=True,
              help="Ray casting threads per worker (embreex releases the GIL). The output does "
                   "not depend on it.")  # fmt: skip
@sensors_option
@artifact_options()
def command(
    sensor,
    cars_profile,
    frames,
    seed,
    workers,
    executor,
    ray_address,
    threads,
    out,
    sensors_path,
    no_progress,
    force,
    dry_run,
):
    """Synthesize a labelled LiDAR domain: street scenes of 2-15 procedural cars with clutter
    (walls, sidewalks, fences, hedges, poles, trees, bushes, containers), scanned with the full
    --sensor pattern.

    Cars are sized around the --cars profile's mean l/w/h with its spread, so `--cars waymo` and
    `--cars kitti` give the size gap of the DALI paper, and the sensor pattern gives the density
    gap. Writes OUT/frames.zarr (points x, y, z, intensity in the sensor frame; ground at
    z = -mount_height under the sensor), OUT/boxes.parquet (every car with >= 1 point: geometric
    center box, yaw, num_points, occlusion, kind, car_model, and the KITTI label fields truncated,
    occluded, alpha, bbox_left/top/right/bottom of a virtual KITTI camera at the sensor, so
    `dali eval --protocol kitti` gives easy/moderate/hard) and OUT/manifest.json.
    """
    from stages.synth import synth

    outcome = synth(
        out, sensor=sensor, cars_profile=cars_profile, frames=frames, seed=seed, workers=workers,
        threads=threads, sensors_path=sensors_path, force=force, dry_run=dry_run,
        executor=executor, ray_address=ray_address, progress=not no_progress,
    )  # fmt: skip
    if (counts := ran_counts(outcome)) is not None:
        lwh = counts["mean_label_lwh_m"]
        click.echo(
            f"  {counts['frames']} frames, {counts['points']} points, {counts['labels']} cars "
            f"({counts['labels_per_frame']} per frame)"
            + (f", mean l/w/h {lwh[0]:.2f}/{lwh[1]:.2f}/{lwh[2]:.2f} m" if lwh else "")
            + f", {outcome.manifest['timings']['frames_per_second']} frames/s"
        )
