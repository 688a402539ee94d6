"""`dali sensors`: list the sensor profiles as a table."""

from __future__ import annotations

import functools

import click

from dali_cli.commands.common import sensors_option
from dali_cli.sensors import load_profiles


@click.command(name="sensors")
@functools.partial(sensors_option, shown=True)
def command(sensors_path: str | None) -> None:
    """List the LiDAR profiles of sensors.toml (or --sensors PATH): beams, elevation range,
    points per beam, mount height, range, noise, dropout and mean car size."""
    profiles = load_profiles(sensors_path)
    header = (
        "profile",
        "beams",
        "elev deg",
        "pts/beam",
        "rays",
        "mount m",
        "range m",
        "noise m",
        "dropout",
        "car l,w,h m",
    )
    rows = [header]
    for name, p in profiles.items():
        rows.append(
            (
                name,
                str(p.beams),
                f"{p.elevations_deg[0]:.1f}..{p.elevations_deg[-1]:.1f}",
                str(p.points_per_beam),
                str(p.num_rays),
                f"{p.mount_height_m:.2f}",
                f"{p.max_range_m:.0f}",
                f"{p.range_noise_sigma_m:.3f}",
                f"{p.ray_dropout:.2f}",
                ",".join(f"{v:.2f}" for v in p.car_mean_lwh_m),
            )
        )
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    for index, row in enumerate(rows):
        click.echo(
            "  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip()
        )
        if index == 0:
            click.echo("  ".join("-" * width for width in widths))
