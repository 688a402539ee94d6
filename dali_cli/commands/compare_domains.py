"""`dali compare-domains`: how alike several frame sets look (real vs synthetic, source vs
target), as a table of point and car statistics, and optionally as JSON and plots."""

from __future__ import annotations

from pathlib import Path

import click

from dali_cli.commands.kinds import VIEW_DEG, named_path

EPILOG = """\b
Each DOMAIN is a frame set directory, DIR or NAME=DIR (named after the directory when no NAME
is given); its boxes.parquet, when present, gives the cars (rows labelled --label). Only points
and car centres within +-VIEW/2 degrees of the sensor's forward axis count (--view-deg 80: about
a KITTI camera's width; 360: the full circle). A car counts when at least one point in view lies
in its box.

\b
Statistics (per frame set): frames; mean points per frame in view; intensity mean, median and
90th percentile; median point height (sensor z, m: the ground lies near -mount height); median
point range (m, in the ground plane); cars per frame in view; cars beyond 40 m / all cars; median
points per car at 10-20, 20-30, 30-40 and 40-60 m (and how many cars each band holds); how far the
car surface sits inside its box: the median depth of the points on each car's end face and side
face turned to the sensor (cars with >= 40 points; real KITTI cars: about 0.14 and 0.08 m).

\b
Output: the table on stdout. --out DIR (a new directory, or one this command wrote) also gets
domains.json ({"settings", "domains": {NAME: {"path", statistic: value}}}), intensity.png,
height.png, range.png (point densities), car_range.png (cars per frame by range) and
points_per_car.png (points per car against range), written atomically with a manifest.
"""


@click.command(name="compare-domains", epilog=EPILOG)
@click.argument("domains", nargs=-1, required=True, metavar="DOMAIN...")
@click.option("--view-deg", type=VIEW_DEG, default=80.0,
              show_default=True,
              help="Horizontal view in front of the sensor (degrees, centred on +x); "
                   "360 keeps everything.")  # fmt: skip
@click.option("--label", default="Car", show_default=True, help="Box label counted as a car.")
@click.option("--max-frames", type=click.IntRange(min=1), default=None,
              help="Use each frame set's first N frames only. Default: all.")  # fmt: skip
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Also write domains.json and the distribution plots here.")  # fmt: skip
@click.option("--force", is_flag=True, help="Rewrite --out even when it is up to date.")
def command(domains, view_deg, label, max_frames, out, force):
    """Point and car statistics of frame sets side by side: points in view, intensity, height
    and range of the points, cars per frame and points per car by range."""
    from dali_cli.reporting.domains import format_table
    from stages.compare_domains import compare_domains

    named = [named_path(value, "DOMAIN", directory=True) for value in domains]
    names = [name for name, _ in named]
    if len(set(names)) != len(names):
        raise click.BadParameter(f"names must differ, got {', '.join(names)}", param_hint="DOMAIN")
    document, _ = compare_domains(
        named,
        view_deg=None if view_deg >= 360 else view_deg,
        label=label,
        max_frames=max_frames,
        out=out,
        force=force,
    )
    view = "full circle" if view_deg >= 360 else f"+-{view_deg / 2:g} deg in front"
    click.echo(f"points and cars in view: {view}; cars: boxes labelled {label}")
    click.echo(format_table([(name, values) for name, values in document["domains"].items()]))
