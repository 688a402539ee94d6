"""`dali track-pseudo`: pseudo labels kept where they persist over a scan sequence."""

from __future__ import annotations

import click

from dali_cli.commands import common
from dali_cli.commands.kinds import DISTANCE_M, MARGIN_M
from dali_cli.labels.tracks import TRACK_SCORE_MIN, TrackParams

DEFAULTS = TrackParams()


@click.command(name="track-pseudo")
@common.input_dir_option("--pseudo", help="Pseudo labels of `dali pseudo-label` on DATA (best made "
                         "with a low `pseudo-label --score-min`, e.g. 0.1: the tracks do the filtering).")  # fmt: skip
@common.data_option("target", help="The target frame set the pseudo labels were made on, with "
                    "its scans' LiDAR poses (sequence.parquet: `dali import kitti-raw --poses`, or "
                         "kitti-odometry with poses and calib.txt) unless --poses gives them.")  # fmt: skip
@common.input_dir_option("--poses", "poses_dir", required=False,
                         help="Read the scans' LiDAR poses (and recordings) from this directory's "
                              "sequence.parquet instead of DATA's: a `dali register` output.")  # fmt: skip
@click.option("--track-score-min", type=common.FRACTION, default=TRACK_SCORE_MIN, show_default=True,
              help="Keep a parked car whose boxes' median score, a moving track whose mean "
                   "score, is at least this.")  # fmt: skip
@common.tuning_option("--gate-m", type=DISTANCE_M, default=DEFAULTS.gate_m,
                      show_default=True, help="BEV distance (m) within which a box joins a track.")  # fmt: skip
@common.tuning_option("--max-gap", type=click.IntRange(min=0), default=DEFAULTS.max_gap,
                      show_default=True, help="Scans a track may miss before it ends.")  # fmt: skip
@common.tuning_option("--parked-m-per-frame", type=MARGIN_M, default=DEFAULTS.parked_m_per_frame,
                      show_default=True, help="A track moving less than this (m a scan) is parked.")  # fmt: skip
@common.tuning_option("--min-hits", type=click.IntRange(min=1), default=DEFAULTS.min_hits,
                      show_default=True, help="Scans a car must be found in (else it is clutter).")  # fmt: skip
@common.tuning_option("--min-points", type=click.IntRange(min=1), default=DEFAULTS.min_points,
                      show_default=True, help="Points a scan must hold in a parked car's box for the "
                                              "box to be placed there.")  # fmt: skip
@common.artifact_options(progress=False)
def command(pseudo, target, poses_dir, out, track_score_min, force, dry_run, **params):
    """Keep the pseudo boxes that persist over DATA's scans: the boxes go into one world frame
    by the scans' poses and are linked scan by scan (nearest within --gate-m of where the
    track's velocity puts it); a parked car (its track moves < --parked-m-per-frame a scan; its
    fragments within --gate-m merged) found in >= --min-hits scans becomes one world box
    (median centre and size, mean heading axis) placed in every scan where it holds
    >= --min-points points, including the scans the detector missed it in; boxes of moving
    tracks with >= --min-hits hits are kept as they are; every other box is dropped.

    Reads PSEUDO/boxes.parquet and scale.json, DATA/frames.zarr and DATA/sequence.parquet
    or POSES/sequence.parquet (never DATA's labels). A merged DATA is tracked drive by
    drive (its sequence table's recording): scans of different drives are never linked. Writes OUT/boxes.parquet (pseudo-label's columns, score = the car's
    or track's score, plus track = the car's id and parked), OUT/scale.json (PSEUDO's),
    OUT/summary.json (counts) and manifest.json: ppcg-rc, ppcg-cf and self-train read OUT as
    they read PSEUDO.
    """
    from stages.track_pseudo import track_pseudo

    outcome = track_pseudo(
        pseudo, target, out, track_score_min=track_score_min, params=TrackParams(**params),
        poses_dir=poses_dir, force=force, dry_run=dry_run,
    )  # fmt: skip
    if (counts := common.ran_counts(outcome)) is not None:
        click.echo(
            f"track-pseudo: {counts['input_boxes']} boxes -> {counts['boxes']} "
            f"({counts['parked_cars']} parked cars placed {counts['boxes_placed']} times, "
            f"{counts['moving_tracks']} moving tracks)"
        )
