"""`dali register`: each scan's LiDAR pose by scan registration."""

from __future__ import annotations

import click

from dali_cli.commands.common import (
    artifact_options,
    data_option,
    ran_counts,
    tuning_option,
)
from dali_cli.commands.kinds import DISTANCE_M, MARGIN_M, TOLERANCE
from dali_cli.registration import RegistrationParams

DEFAULTS = RegistrationParams()


@click.command(name="register")
@data_option("target", help="The frame set whose scans to register (frames.zarr; its "
             "sequence.parquet, when it has one, gives the scans' order and recordings).")  # fmt: skip
@tuning_option("--voxel-m", type=DISTANCE_M, default=DEFAULTS.voxel_m, show_default=True,
               help="Map voxel (m); a scan is kept at half of it and registered at 1.5 times it.")  # fmt: skip
@tuning_option("--min-range-m", type=DISTANCE_M, default=DEFAULTS.min_range_m,
               show_default=True, help="Points nearer the sensor (m) are dropped (the ego car).")  # fmt: skip
@tuning_option("--max-range-m", type=DISTANCE_M, default=DEFAULTS.max_range_m,
               show_default=True, help="Points farther from the sensor (m) are dropped, and the "
                                       "map is kept within this of the latest scan.")  # fmt: skip
@tuning_option("--max-correspondence-m", type=DISTANCE_M,
               default=DEFAULTS.max_correspondence_m, show_default=True,
               help="A point farther (m) from its nearest map point has no residual; the first "
                    "robust kernel scale.")  # fmt: skip
@tuning_option("--kernel-m", type=MARGIN_M, default=DEFAULTS.kernel_m, show_default=True,
               help="The final Geman-McClure scale (m) of the residuals.")  # fmt: skip
@tuning_option("--max-iterations", type=click.IntRange(1, 10_000),
               default=DEFAULTS.max_iterations, show_default=True,
               help="ICP updates a scan may take.")  # fmt: skip
@tuning_option("--tolerance", type=TOLERANCE, default=DEFAULTS.tolerance, show_default=True,
               help="ICP stops at an update smaller than this (m + rad).")  # fmt: skip
@tuning_option("--max-points-per-voxel", type=click.IntRange(1, 10_000),
               default=DEFAULTS.max_points_per_voxel, show_default=True,
               help="Map points a voxel keeps (the oldest).")  # fmt: skip
@artifact_options()
def command(target, out, force, dry_run, no_progress, **params):
    """Estimate each scan's LiDAR pose by registering it to a local map of the scans before it
    (point-to-plane ICP with a constant-velocity motion prior and a robust kernel, on points
    3-80 m from the sensor), for a target recorded without GPS/IMU poses.

    A merged DATA (`dali merge`) is registered recording by recording (its sequence table's
    recording, or the frame ids' NAME- prefix), each from its own first scan. Scans are taken
    in the order of the sequence table's index; a scan the table lacks (or a target without
    one) by the number its frame id ends with, else by frame id. Writes OUT/sequence.parquet
    (DATA's table with the LiDAR poses replaced, or a new one: each scan's pose in its
    recording's first scan), OUT/summary.json (per recording: scans, path length, median step,
    ICP iterations, scans that did not converge) and manifest.json; never writes in DATA.
    `dali track-pseudo --poses OUT` reads the poses.
    """
    from stages.register import register

    outcome = register(
        target,
        out,
        params=RegistrationParams(**params),
        force=force,
        dry_run=dry_run,
        progress=not no_progress,
    )
    if (counts := ran_counts(outcome)) is not None:
        click.echo(
            f"register: {counts['frames']} scans in {counts['recordings']} recording(s), "
            f"{counts['path_length_m']:.1f} m, {counts['not_converged']} not converged"
        )
