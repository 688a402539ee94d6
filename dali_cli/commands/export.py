"""`dali export kitti|openpcdet|model`: dali artifacts -> other tools' formats."""

from __future__ import annotations

from pathlib import Path

import click

from dali_cli.commands import common
from dali_cli.commands.kinds import SCALE


@click.group(name="export")
def command() -> None:
    """Export dali boxes, frames and models to other tools' formats: KITTI label_2 files
    (kitti), OpenPCDet's custom layout (openpcdet), the detector as ONNX (model). Each export is
    a stage with a manifest.json, written atomically and skipped when up to date."""


MAX_IMAGE_PX = 100_000  # pixels on a side of any camera's image


def _parse_image_size(_ctx, _param, value: str | None) -> tuple[int, int] | None:
    if value is None:
        return None
    try:
        width, height = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected WIDTHxHEIGHT in pixels, got {value!r}") from None
    if width <= 0 or height <= 0:
        raise click.BadParameter(f"image size must be positive, got {value!r}")
    if width > MAX_IMAGE_PX or height > MAX_IMAGE_PX:
        raise click.BadParameter(
            f"image size {width}x{height}: at most {MAX_IMAGE_PX} pixels a side (no camera has more)"
        )
    return width, height


@command.command(name="kitti", short_help="KITTI label_2 files (LiDAR -> camera through calib).")
@click.argument("boxes_dir", type=click.Path(exists=True))
@click.option("--calib-root", type=click.Path(exists=True, file_okay=False), required=True,
              help="KITTI root (ROOT/SPLIT/calib or ROOT/calib) or the calib directory itself.")  # fmt: skip
@common.choice_option("--split", choices=["training", "testing"], default="training",
                      help="Split directory under --calib-root.")  # fmt: skip
@click.option("--frames", "frames_dir", type=click.Path(exists=True, file_okay=False),
              default=None,
              help="FrameSet whose frames all get a file (frames without boxes an empty one). "
                   "Default: BOXES_DIR when it holds frames.zarr, else the frames of the box "
                   "table.")  # fmt: skip
@common.tuning_option("--image-size", default=None, callback=_parse_image_size,
                     help="WIDTHxHEIGHT for clipping 2D boxes. Default: each frame's image_2 PNG, else "
                          "1242x375.")  # fmt: skip
@click.option(
    "--score-min", type=common.FRACTION, default=None, help="Export only boxes with score >= this."
)
@click.option("--keep-outside", is_flag=True,
              help="Also write boxes behind the camera or outside the image (default: left out, "
                   "counted).")  # fmt: skip
@click.option("--project-bbox", is_flag=True,
              help="Always compute alpha and the 2D box from the 3D box, even when the table has "
                   "the KITTI label columns (an imported label set).")  # fmt: skip
@click.option("--no-score", is_flag=True,
              help="Write 15-field lines (ground-truth format) without the score.")  # fmt: skip
@common.artifact_options()
def kitti_command(
    boxes_dir,
    calib_root,
    split,
    frames_dir,
    image_size,
    score_min,
    keep_outside,
    project_bbox,
    no_score,
    out,
    no_progress,
    force,
    dry_run,
):
    """Write BOXES_DIR/boxes.parquet as KITTI label_2 files OUT/data/<frame>.txt.

    Boxes go from the LiDAR frame to the rectified camera through each frame's calib
    (CALIB_ROOT/.../calib/<frame>.txt); the 2D box is the projection of the 8 corners clipped to
    the image; alpha = rotation_y - atan2(x, z). Lines have 16 fields (the score last) unless
    --no-score. An imported label set (with the KITTI columns) is written back as read,
    DontCare rows included, unless --project-bbox. Score the files with the KITTI devkit or OpenPCDet's
    kitti_eval, or re-import them with `dali import kitti ROOT --label-dir OUT/data`.
    """
    from stages.export import export_kitti

    outcome = export_kitti(
        boxes_dir, calib_root, out, split=split, frames_dir=frames_dir, image_size=image_size,
        score_min=score_min, keep_outside=keep_outside, project_bbox=project_bbox,
        with_score=not no_score, force=force, dry_run=dry_run, progress=not no_progress,
    )  # fmt: skip
    if (counts := common.ran_counts(outcome)) is not None:
        click.echo(
            f"  {counts['boxes_written']} boxes in {counts['frames']} files under {Path(out) / 'data'}, "
            f"{counts['boxes_outside_image']} outside the image left out"
        )


@command.command(
    name="openpcdet", short_help="OpenPCDet custom format (points/*.npy, labels/*.txt)."
)
@click.argument("data_dir", type=click.Path(exists=True, file_okay=False))
@click.option("--boxes", "boxes_dir", type=click.Path(exists=True), default=None,
              help="Box table to write as labels. Default: DATA_DIR/boxes.parquet when present.")  # fmt: skip
@click.option("--split", default=None, help="Also write ImageSets/SPLIT.txt listing the frames.")
@click.option(
    "--score-min", type=common.FRACTION, default=None, help="Write only boxes with score >= this."
)
@common.artifact_options(progress=False)
def openpcdet_command(data_dir, boxes_dir, split, score_min, out, force, dry_run):
    """Write the FrameSet DATA_DIR in OpenPCDet's custom format: OUT/points/<frame>.npy
    ((n, 4) float32) and, with boxes, OUT/labels/<frame>.txt (x y z dx dy dz heading class)."""
    from stages.export import export_openpcdet

    export_openpcdet(
        data_dir,
        out,
        boxes_dir=boxes_dir,
        split=split,
        score_min=score_min,
        force=force,
        dry_run=dry_run,
    )


@command.command(name="model", short_help="The detector's network as ONNX (onnxruntime).")
@click.argument("model_dir", type=click.Path(exists=True, file_okay=False))
@click.option("--onnx", "as_onnx", is_flag=True,
              help="Export as ONNX (opset 18): the one format, so also without this flag.")  # fmt: skip
@click.option("--scale", type=SCALE, default=None,
              help="PTSN scale whose grid the graph runs on. Default: MODEL_DIR/scale.json, "
                   "else 1.")  # fmt: skip
@common.scale_from_option(tuning=True)
@common.artifact_options(progress=False)
def model_command(model_dir, as_onnx, scale, scale_from, out, force, dry_run):
    """Write the detector of MODEL_DIR as OUT/detector.onnx (one frame's pillarized points ->
    head maps) and OUT/refiner.onnx (box point features -> residuals and IoU), with OUT/onnx.json
    (opset, grid, inputs; docs/detector.md "ONNX"). Run it with
    dali_cli.detector.onnx_export.OnnxDetector (at the mount height of the sensor the model is
    for, onnx.json's config), or read onnx.json to feed another runtime."""
    del as_onnx  # ONNX with or without the flag: the one format of a model
    from stages.export import export_model

    outcome = export_model(
        model_dir, out, scale=scale, scale_from=scale_from, force=force, dry_run=dry_run
    )
    if (counts := common.ran_counts(outcome)) is not None:
        click.echo(f"  opset {counts['opset']}, grid {counts['rows']} x {counts['cols']} pillars")
