"""Stage synth: a labelled synthetic LiDAR domain (frames.zarr, boxes.parquet, manifest.json) of
street scenes scanned with a sensor profile's pattern (dali_cli.synth)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

from dali_cli.store.manifest import StageOutcome, run_stage


def synth(
    out: str | Path,
    *,
    sensor: str,
    cars_profile: str | None = None,
    frames: int = 24,
    seed: int = 0,
    workers: int | None = None,
    threads: int | None = None,
    sensors_path: str | None = None,
    force: bool = False,
    dry_run: bool = False,
    executor: str = "local",
    ray_address: str | None = None,
    progress: bool = True,
) -> StageOutcome:
    """`frames` scenes scanned with `sensor`'s pattern, cars sized by `cars_profile` (default:
    the sensor's own); frame k depends only on (seed, k), whatever the engine (`executor`,
    `workers`, `ray_address`: dali_cli.executors) and `threads`; `progress`: a progress bar on
    stderr."""
    from dali_cli.executors import make_executor, run_on
    from dali_cli.runtime.cores import available_cores
    from dali_cli.runtime.limits import check_limit
    from dali_cli.sensors import get_profile
    from dali_cli.synth import build_synth

    check_limit("frames", frames, "--frames")
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
    return run_stage(
        "synth",
        out,
        {},
        params,
        lambda tmp: run_on(
            engine,
            "synth",
            lambda pool: build_synth(
                tmp,
                sensor_profile,
                cars,
                frames,
                seed,
                progress=progress,
                threads=threads,
                executor=pool,
            ),
        ),
        force=force,
        dry_run=dry_run,
        seed=seed,
    )
