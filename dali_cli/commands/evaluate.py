"""`dali eval`: KITTI-protocol AP_BEV / AP_3D of predictions against labels."""

from __future__ import annotations

from pathlib import Path

import click

from dali_cli.commands.common import (
    FRACTION,
    choice_option,
    executor_options,
    no_progress_option,
    scale_from_option,
    stage_options,
    tuning_option,
    workers_option,
)
from dali_cli.commands.detector_options import (
    device_options,
    inference_threads_option,
    score_min_option,
)
from dali_cli.commands.kinds import SCALE
from dali_cli.commands.protocol_options import PROTOCOLS_HELP, calib_option, protocol_options

EPILOG = (
    """\b
Inputs (--pred, --gt): a box-table directory (boxes.parquet), a .parquet file, or a KITTI
label_2-style directory of <frame>.txt files (predictions with a 16th score field).
With --model MODEL --data DIR the predictions come from running the detector on DIR's frames
(at --scale, or at the PTSN scale in PTSN_DIR/scale.json) and DIR/boxes.parquet is the ground
truth unless --gt is given.

"""
    + PROTOCOLS_HELP
    + """
\b
Size correction (a tuning option, shown above: --size-correction per-dim --scale-from
PTSN_DIR): one isotropic PTSN scale
matches the volume of the mean predicted car, not each dimension; the bias left per dimension
(measured: w +0.07, h -0.06 m at 600 frames) costs AP at IoU 0.7. The factors E_est / E_pred at
the chosen scale, both from PTSN_DIR/scale.json (the sweep's own numbers on the unlabelled target
training frames, no target label), resize every predicted car, bottom face kept. With --pred
instead of --model, --scale-from gives only these factors (correcting saved predictions).
E_pred is the mean of every prediction above the sweep's --score-min, false ones included: where
that mean is already close to E_est the factors can move true boxes off (600 frames: +2.0
AP_3D@0.7 on the Waymo-like task, three seeds; -1.7 on the nuScenes-like task, one seed;
docs/RESULTS.md).

\b
Output: the AP table on stdout; --out FILE writes metrics.json
({"Car": {"iou", "recall_positions", "bev": {...}, "3d": {...}, "counts": {...}, "curves"}},
one more block "Car@<iou>" per further --iou, "sizes": {"pred", "gt"} mean l/w/h in metres of
the class (predictions: score >= --size-score-min), "scale" (with --model; with --pred the
scale of the eval that saved them, when its metrics.json says), with a size
correction "size_correction" (factors, E_est, E_pred and the scale.json they came from),
"errors": the error breakdown (box errors of the matches, false positives by kind and the AP
each kind costs; docs/evaluation.md). With --calib each block also holds "bbox" (AP_2D) and its
"aos" is KITTI's on the image matches ("aos_matching": "image", else "bev").
"""
)


@click.command(name="eval", epilog=EPILOG)
@click.option("--pred", "pred_path", type=click.Path(exists=True, path_type=Path),
              help="Predictions (box table or label_2 dir).")  # fmt: skip
@click.option("--gt", "gt_path", type=click.Path(exists=True, path_type=Path),
              help="Ground truth (box table or label_2 dir).")  # fmt: skip
@click.option("--model", type=click.Path(exists=True, file_okay=False),
              help="Detector checkpoint dir: predict first.")  # fmt: skip
@click.option("--data", type=click.Path(exists=True, file_okay=False),
              help="Frame set to run --model on (its boxes.parquet is the default --gt).")  # fmt: skip
@click.option("--scale", type=SCALE, default=None,
              help="PTSN scale for --model inference (default 1).")  # fmt: skip
@scale_from_option()
@click.option("--iou", "ious", type=FRACTION, multiple=True, default=(0.7,), show_default=True,
              help="IoU threshold (a match needs IoU > this); repeat for several (--iou 0.7 "
                   "--iou 0.5).")  # fmt: skip
@score_min_option("size_score_min", "Predictions with at least this score enter the mean "
                                    "predicted size in metrics.json (AP counts every "
                                    "prediction).", flag="--size-score-min")  # fmt: skip
@protocol_options
@calib_option(
    "With it, KITTI's image side as its devkit computes it: each prediction's 2D box "
    "and alpha through its frame's calibration, AP_2D and AOS on the image matches "
    "(the labels' own 2D boxes and alpha; --protocol kitti)."
)
@choice_option("--size-correction", choices=["none", "per-dim"], default="none", tuning=True,
               help="per-dim: resize the predicted cars per dimension (bottom face kept) by "
                    "E_est / E_pred(ŝ) of --scale-from's sweep before evaluating: the test-time "
                    "half of PTSN's size bias, label-free (see below).")  # fmt: skip
@click.option("--out", type=click.Path(path_type=Path),
              help="A metrics file (FILE.json), or an artifact directory (any other path): "
                   "DIR/metrics.json, DIR/predictions.parquet and DIR/manifest.json, skipped "
                   "when up to date (what make uses).")  # fmt: skip
@tuning_option("--save-predictions/--no-save-predictions", default=True, show_default=True,
              help="With --model and --out: also write the predictions (all scores) as "
                   "predictions.parquet beside metrics.json (read by `dali report` for size "
                   "plots).")  # fmt: skip
@device_options
@inference_threads_option
@workers_option("1")
@executor_options
@no_progress_option
@stage_options
def command(
    pred_path,
    gt_path,
    model,
    data,
    scale,
    scale_from,
    ious,
    size_score_min,
    recall_positions,
    protocol,
    front_only,
    class_name,
    min_gt_points,
    calib,
    size_correction,
    out,
    save_predictions,
    device,
    precision,
    threads,
    workers,
    executor,
    ray_address,
    force,
    dry_run,
    no_progress,
):
    """Average precision (KITTI protocol, BEV and 3D, float64 rotated IoU) of predictions.
    With --model, the detector runs on --executor with --workers."""
    from dali_cli.evaluation.errors import format_breakdown
    from dali_cli.evaluation.evaluate import format_table
    from stages.eval import ERRORS_KEY, run_eval

    result = run_eval(
        pred_path=pred_path, gt_path=gt_path, model=model, data=data, scale=scale,
        scale_from=scale_from, ious=tuple(ious), size_score_min=size_score_min,
        recall_positions=int(recall_positions), protocol=protocol, front_only=front_only,
        class_name=class_name, min_gt_points=min_gt_points, out=out,
        save_predictions=save_predictions, device=device, precision=precision, executor=executor,
        workers=workers, ray_address=ray_address, force=force, dry_run=dry_run,
        progress=not no_progress, size_correction=size_correction, calib=calib,
        threads=threads,
    )  # fmt: skip
    if result.status == "dry-run":
        return
    blocks = {
        k: v
        for k, v in result.metrics.items()
        if k not in ("sizes", "scale", "runtime", "size_correction", ERRORS_KEY)
    }
    click.echo(format_table(blocks))
    if ERRORS_KEY in result.metrics:  # absent from artifacts written before it existed
        click.echo(format_breakdown(result.metrics[ERRORS_KEY]))
    if result.status == "ran" and out is not None and out.suffix == ".json":
        click.echo(f"wrote {out}", err=True)
