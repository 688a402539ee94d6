"""`dali merge`: several frame sets as one, frame ids prefixed with their set's name."""

from __future__ import annotations

import click

from dali_cli.commands.common import artifact_options, ran_counts


@click.command(name="merge")
@click.option("--in", "specs", multiple=True, required=True, metavar="[NAME=]DIR",
              help="A frame set to merge (repeat, in order). NAME (default: DIR's name) starts "
                   "its frame ids: NAME-<frame id>.")  # fmt: skip
@click.option("--no-labels", is_flag=True,
              help="Merge the frames only, without any set's boxes (an unlabeled target).")  # fmt: skip
@artifact_options()
def command(specs, no_labels, out, force, dry_run, no_progress):
    """Write the frames of every --in set as one frame set OUT, e.g. an unlabeled target of
    several drives: `dali merge --in 2011_09_26_drive_0005=data/d0005 --in data/odometry_04
    --out data/target`.

    Frame ids become NAME-<frame id> (2011_09_26_drive_0005-0000000012), unique across the sets
    and naming their set. The sets must share the sensor profile and the kind of point values
    (KITTI's reflectance from kitti, kitti-raw and kitti-odometry imports); a mix is an error.
    Boxes are merged when every set has boxes.parquet (a mix of labelled and unlabeled sets is
    an error: --no-labels drops them all), the importers' per-frame sequence.parquet (times,
    poses) when present, with recording = NAME (each set's poses stay in its own world frame;
    track-pseudo tracks each recording on its own). Writes OUT/frames.zarr, OUT/boxes.parquet, OUT/sequence.parquet and
    OUT/manifest.json (frames per set).
    """
    from stages.merge import merge

    outcome = merge(
        specs, out, labels=not no_labels, force=force, dry_run=dry_run, progress=not no_progress
    )
    if (counts := ran_counts(outcome)) is not None:
        sets = ", ".join(f"{name} {n}" for name, n in counts["frames_by_set"].items())
        click.echo(f"  {counts['frames']} frames ({sets}), {counts.get('boxes', 0)} boxes")
