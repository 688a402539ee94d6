"""`dali view`: one frame with boxes of several sources as a PNG."""

from __future__ import annotations

from pathlib import Path

import click

from dali_cli.commands.common import FRACTION, choice_option, tuning_option
from dali_cli.commands.kinds import DISTANCE_M, named_path


@click.command(name="view")
@click.argument("data_dir", type=click.Path(exists=True, file_okay=False))
@click.option("--frame", "frame", default=None,
              help="Frame id; a number that is not an id is taken as the frame's index. Needed "
                   "for a PNG; a recording holds every frame.")  # fmt: skip
@click.option("--boxes", "boxes", multiple=True,
              help="Box table to draw, DIR or NAME=DIR (repeatable; each gets its own colour). "
                   "DATA_DIR's own boxes.parquet is drawn first unless --no-own-boxes.")  # fmt: skip
@click.option("--no-own-boxes", is_flag=True, help="Do not draw DATA_DIR/boxes.parquet.")
@click.option(
    "--score-min", type=FRACTION, default=None, help="Draw only boxes with score >= this."
)
@click.option("--side", is_flag=True, help="Add a side view (x-z) under the bird's-eye view.")
@click.option("--range-m", type=DISTANCE_M, default=None,
              help="Show x, y in [-R, R]. Default: fitted to the points and boxes.")  # fmt: skip
@choice_option("--colour-by", choices=["z", "intensity"], default="z", help="Point colour.",
               tuning=True)  # fmt: skip
@tuning_option("--annotate", is_flag=True, help="Write each box's score (or label) at its centre.")
@tuning_option("--width-px", type=click.IntRange(min=200, max=8000), default=1200,
              show_default=True, help="Image width in pixels.")  # fmt: skip
@click.option("--out", "out", type=click.Path(dir_okay=False), default=None,
              help="PNG file to write.")  # fmt: skip
@click.option("--rerun", "rerun_out", type=click.Path(dir_okay=False), default=None,
              help="Write a Rerun recording (.rrd) of every frame instead: scans over time, each "
                   "table's boxes (by score; TP / FP / missed against DATA_DIR's labels; tracks "
                   "by id), the ego path where there are poses. Open it with `rerun FILE`.")  # fmt: skip
def command(
    data_dir,
    frame,
    boxes,
    no_own_boxes,
    score_min,
    side,
    range_m,
    colour_by,
    annotate,
    width_px,
    out,
    rerun_out,
):
    """Draw frame FRAME of the FrameSet DATA_DIR as a PNG: bird's-eye view of the points (x right,
    y up, coloured by height or intensity) with the boxes of each box table in its own colour,
    Car solid, other labels dashed, a tick towards each box's front; --side adds an x-z view.
    For checking imported data and pseudo labels by eye. Writes only OUT (or the recording)."""
    from dali_cli.labels.plausibility import refuse_implausible_table
    from dali_cli.store.artifacts import (
        BOXES_NAME,
        ArtifactError,
        FrameSet,
        check_frames_known,
        read_boxes,
    )

    if (out is None) == (rerun_out is None):
        raise click.UsageError("give one of --out (a PNG of --frame) and --rerun (a recording)")
    if rerun_out is not None:
        return record(data_dir, boxes, no_own_boxes, score_min, rerun_out)
    if frame is None:
        raise click.UsageError("--frame: which frame to draw (a recording needs none: --rerun)")

    try:
        import matplotlib  # noqa: F401  (a dev extra, not a core dependency)
    except ImportError:
        raise click.ClickException("dali view needs matplotlib: pip install matplotlib") from None
    from dali_cli.reporting.view import BoxSet, render_frame
    from dali_cli.store.output_paths import check_file_output, is_dali_png

    box_inputs = [named_path(value, "--boxes")[1] for value in boxes]
    check_file_output(
        out, {"data": data_dir, "boxes": box_inputs}, is_dali_png, "a PNG dali view wrote"
    )
    frames = FrameSet(data_dir)
    frame_id = frame
    if frame not in frames.frame_ids:
        if not frame.isdigit() or int(frame) >= len(frames):
            raise ArtifactError(f"{frames.path}: no frame '{frame}' ({len(frames)} frames)")
        frame_id = frames.frame_ids[int(frame)]
    points = frames.frame(frame_id)
    sources = [named_path(value, "--boxes") for value in boxes]
    own = Path(data_dir) / BOXES_NAME
    if not no_own_boxes and (own.exists() or own.is_symlink()):  # a FIFO or dangling link: refused
        sources.insert(0, ("labels", Path(data_dir)))
    box_sets = []
    for name, path in sources:
        whole = read_boxes(path)
        check_frames_known(whole, frames.frame_ids, str(path))
        refuse_implausible_table(whole, str(path))
        table = whole.for_frame(frame_id)
        if score_min is not None:
            table = table.select(table["score"] >= score_min)
        box_sets.append(BoxSet(name, table.boxes, table["label"], table["score"]))
    extent = None if range_m is None else (-range_m, range_m, -range_m, range_m)
    title = f"{Path(data_dir).name} / {frame_id}: {len(points)} points"
    render_frame(points, box_sets, out, title, side, extent, colour_by, width_px, annotate)
    click.echo(
        f"view: wrote {out} ({', '.join(f'{b.name} {len(b.boxes)}' for b in box_sets) or 'no boxes'})"
    )


def record(data_dir, boxes, no_own_boxes: bool, score_min, rerun_out) -> None:
    """`dali view --rerun`: the recording of DATA_DIR with its tables (reporting/recording.py)."""
    try:
        import rerun  # noqa: F401  (an optional extra)
    except ImportError:
        raise click.ClickException(
            "dali view --rerun needs rerun-sdk: pip install rerun-sdk (or pip install 'dali[view]')"
        ) from None
    from dali_cli.reporting.recording import record_frameset
    from dali_cli.store.artifacts import BOXES_NAME
    from dali_cli.store.output_paths import check_file_output, is_dali_recording

    sources = [named_path(value, "--boxes") for value in boxes]
    check_file_output(
        rerun_out, {"data": data_dir, "boxes": [path for _, path in sources]}, is_dali_recording,
        "a recording dali wrote", option="--rerun",
    )  # fmt: skip
    own = Path(data_dir) / BOXES_NAME
    if not no_own_boxes and (own.exists() or own.is_symlink()):
        sources.insert(0, ("labels", Path(data_dir)))
    counts = record_frameset(Path(rerun_out), Path(data_dir), sources, score_min)
    click.echo(
        f"view: wrote {rerun_out} ({counts['frames']} frames, {counts['entities']} entities, "
        f"{counts['boxes']} boxes); open it with: rerun {rerun_out}"
    )
