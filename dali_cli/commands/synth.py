"""`dali synth`: a synthetic labeled domain (FrameSet + boxes.parquet) from a sensor and a car-size profile."""

from __future__ import annotations

import click

from dali_cli.commands.common import (
    executor_options,
    sensors_option,
    stage_options,
    workers_option,
)


@click.command(name="synth")
@click.option(
    "--sensor",
    required=True,
    help="Sensor profile of sensors.toml that scans the scenes (kitti, waymo, nuscenes, ...).",
)
@click.option(
    "--cars",
    "cars_profile",
    default=None,
    help="Profile whose car_mean_lwh_m / car_std_lwh_m size the cars. Default: --sensor.",
)
@click.option("--frames", type=click.IntRange(min=1), required=True, help="Number of frames.")
@click.option(
    "--seed",
    type=int,
    default=0,
    show_default=True,
    help="Run seed; frame k depends only on (seed, k).",
)
@workers_option("the cores available")
@executor_options
@click.option(
    "--threads",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Ray casting threads per worker (embreex releases the GIL). The output does not depend on it.",
)
@click.option("--out", required=True, type=click.Path(file_okay=False), help="Output directory.")
@sensors_option
@stage_options
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
    force,
    dry_run,
):
    """Synthesize a labeled LiDAR domain: street scenes of 5-30 procedural cars with clutter
    (walls, poles, trees, bushes, curbs, containers), scanned with the full --sensor pattern.

    Cars are sized around the --cars profile's mean l/w/h with its spread, so `--cars waymo` and
    `--cars kitti` give the size gap of the DALI paper, and the sensor pattern gives the density
    gap. Writes OUT/frames.zarr (points x, y, z, intensity in the sensor frame; ground at
    z = -mount_height under the sensor), OUT/boxes.parquet (every car with >= 1 point: geometric
    center box, yaw, num_points, occlusion, kind, car_model, and the KITTI label fields truncated,
    occluded, alpha, bbox_left/top/right/bottom of a virtual KITTI camera at the sensor, so
    `dali eval --protocol kitti` gives easy/moderate/hard) and OUT/manifest.json.
    """
    import dataclasses
    import hashlib
    import json

    from dali_cli.executors import make_executor, run_on
    from dali_cli.manifest import run_stage
    from dali_cli.raycast import available_cores
    from dali_cli.sensors import get_profile
    from dali_cli.synth import build_synth

    sensor_profile = get_profile(sensor, sensors_path)
    cars = get_profile(cars_profile or sensor, sensors_path)
    engine = make_executor(
        executor,
        workers or (available_cores() if executor == "local" else None),
        ray_address,
        cpus_per_worker=threads,
    )
    params = {
        "sensor": sensor,
        "cars": cars.name,
        "frames": frames,
        "seed": seed,
        # a digest of the profile's values, so that editing sensors.toml makes the output stale
        "sensor_profile_digest": hashlib.blake2b(
            json.dumps(dataclasses.asdict(sensor_profile), sort_keys=True).encode(), digest_size=8
        ).hexdigest(),
        "cars_lwh_m": {"mean": cars.car_mean_lwh_m, "std": cars.car_std_lwh_m},
    }
    outcome = run_stage(
        "synth",
        out,
        {},
        params,
        lambda tmp: run_on(
            engine,
            "synth",
            lambda pool: build_synth(
                tmp, sensor_profile, cars, frames, seed, threads=threads, executor=pool
            ),
        ),
        force=force,
        dry_run=dry_run,
        seed=seed,
    )
    if outcome.status == "ran":
        counts = outcome.manifest["outputs"]["counts"]
        lwh = counts["mean_label_lwh_m"]
        click.echo(
            f"  {counts['frames']} frames, {counts['points']} points, {counts['labels']} cars "
            f"({counts['labels_per_frame']} per frame)"
            + (f", mean l/w/h {lwh[0]:.2f}/{lwh[1]:.2f}/{lwh[2]:.2f} m" if lwh else "")
            + f", {outcome.manifest['timings']['frames_per_second']} frames/s"
        )
