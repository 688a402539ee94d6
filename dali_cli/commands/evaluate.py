"""`dali eval`: KITTI-protocol AP_BEV / AP_3D of predictions against labels."""

from __future__ import annotations

import json
import os
from pathlib import Path

import click
import numpy as np

from dali_cli.artifacts import BOXES_NAME, BoxTable, FrameSet, read_boxes
from dali_cli.commands.common import device_options, executor_options, workers_option

EPILOG = """\b
Inputs (--pred, --gt): a box-table directory (boxes.parquet), a .parquet file, or a KITTI
label_2-style directory of <frame>.txt files (predictions with a 16th score field).
With --model MODEL --data DIR the predictions come from running the detector on DIR's frames
(at --scale, or at the PTSN scale in PTSN_DIR/scale.json) and DIR/boxes.parquet is the ground
truth unless --gt is given.

\b
Protocols: kitti = easy/moderate/hard from the KITTI label fields (2D box height, occlusion,
truncation); range = all boxes and BEV-distance bands 0-30, 30-50, 50-80 m; st3d = ST3D's
target-domain evaluation (ground truth only in the front 90 deg FOV and the detection range,
every box 'easy'); auto (default) = kitti when the ground truth has the KITTI fields, else range.
dali synth labels carry the KITTI fields (2D box, truncation, occlusion level of a virtual KITTI
camera at the sensor), so --protocol kitti gives easy/moderate/hard on synthetic data too.
--front-only restricts any protocol to that front region, ground truth and predictions alike
(KITTI's clouds are FOV-cropped; dali synth's are 360 degrees). Van ground truths are ignored
for Car; --min-gt-points marks ground-truth cars with fewer points as ignored (neither miss nor
false positive), it never drops them.

\b
Output: the AP table on stdout; --out FILE writes metrics.json
({"Car": {"iou", "recall_positions", "bev": {...}, "3d": {...}, "counts": {...}, "curves"}},
one more block "Car@<iou>" per further --iou, "sizes": {"pred", "gt"} mean l/w/h in metres of
the class (predictions: score >= --size-score-min) and, with --model, "scale").
"""


def _read_table(path: Path, role: str) -> tuple[BoxTable, list[str] | None]:
    """A box table from a parquet dir/file or a label directory, plus the label files' frames."""
    from dali_cli.kitti_label import list_label_frames, read_label_dir

    if path.is_file() and path.suffix == ".parquet":
        return read_boxes(path), None
    if path.is_dir() and (path / BOXES_NAME).is_file():
        return read_boxes(path), None
    if path.is_dir() and (path / "label_2").is_dir():
        path = path / "label_2"
    if path.is_dir() and any(path.glob("*.txt")):
        return read_label_dir(path), list_label_frames(path)
    raise click.BadParameter(
        f"{path}: neither a box table ({BOXES_NAME}) nor a directory of label .txt files",
        param_hint=f"--{role}",
    )


def _read_scale(scale: float | None, scale_from: str | None) -> float:
    if scale is not None and scale_from is not None:
        raise click.UsageError("give either --scale or --scale-from, not both")
    if scale_from is None:
        value = 1.0 if scale is None else scale
    else:
        from dali_cli.scale_file import read_scale

        value, _ = read_scale(scale_from)
    if not value > 0:
        raise click.UsageError(f"the scale must be positive, got {value}")
    return float(value)


def _predict(
    model: str, data: str, scale: float, engine, out: Path | None, device: str, precision: str
) -> BoxTable:
    """The model's predictions on `data`, on `engine` (dali_cli.executors); a parallel engine's
    shards go to a temporary folder beside --out (which workers must see), removed after."""
    import shutil
    import tempfile

    try:
        from dali_cli.detector import predict_frameset
    except ImportError as error:
        raise click.ClickException(f"the detector is not available ({error})") from None
    from dali_cli.executors import run_on

    if engine.serial:  # the reference path: in this process
        return run_on(
            engine,
            "eval",
            lambda _: predict_frameset(
                model,
                data,
                scale=scale,
                score_min=0.0,
                progress=True,
                device=device,
                precision=precision,
            ),
        )
    parent = Path(out).parent if out is not None else None
    if parent is not None:
        parent.mkdir(parents=True, exist_ok=True)
    where = Path(tempfile.mkdtemp(prefix=".dali-eval-shards-", dir=parent))
    try:
        return run_on(
            engine,
            "eval",
            lambda pool: predict_frameset(
                model, data, scale=scale, score_min=0.0, progress=True, executor=pool,
                shards_dir=where, device=device, precision=precision,
            ),
        )  # fmt: skip
    finally:
        shutil.rmtree(where, ignore_errors=True)


def _write_atomically(path: Path, write) -> None:
    """`write(partial_path)`, then rename onto `path`: a reader never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".part")
    write(partial)
    os.replace(partial, path)


def _write_json(path: Path, document: dict) -> None:
    _write_atomically(
        path, lambda partial: partial.write_text(json.dumps(document, indent=2) + "\n")
    )


@click.command(name="eval", epilog=EPILOG)
@click.option(
    "--pred",
    "pred_path",
    type=click.Path(exists=True, path_type=Path),
    help="Predictions (box table or label_2 dir).",
)
@click.option(
    "--gt",
    "gt_path",
    type=click.Path(exists=True, path_type=Path),
    help="Ground truth (box table or label_2 dir).",
)
@click.option(
    "--model",
    type=click.Path(exists=True, file_okay=False),
    help="Detector checkpoint dir: predict first.",
)
@click.option(
    "--data",
    type=click.Path(exists=True, file_okay=False),
    help="Frame set to run --model on (its boxes.parquet is the default --gt).",
)
@click.option(
    "--scale", type=float, default=None, help="PTSN scale for --model inference (default 1)."
)
@click.option(
    "--scale-from",
    type=click.Path(exists=True, file_okay=False),
    help="Read the scale from PTSN_DIR/scale.json.",
)
@click.option(
    "--iou",
    "ious",
    type=float,
    multiple=True,
    default=(0.7,),
    show_default=True,
    help="IoU threshold (a match needs IoU > this); repeat for several (--iou 0.7 --iou 0.5).",
)
@click.option(
    "--size-score-min",
    type=click.FloatRange(0.0, 1.0),
    default=0.3,
    show_default=True,
    help="Predictions with at least this score enter the mean predicted size in metrics.json.",
)
@click.option(
    "--recall-positions",
    type=click.Choice(["40", "11"]),
    default="40",
    show_default=True,
    help="R40 or R11 AP.",
)
@click.option(
    "--protocol",
    type=click.Choice(["auto", "kitti", "range", "st3d"]),
    default="auto",
    show_default=True,
    help="Difficulty filters (see below).",
)
@click.option(
    "--front-only",
    "--crop-predictions",
    "front_only",
    is_flag=True,
    help="Keep only ground truth and predictions centred in the front 90 deg FOV and the detection "
    "range (x 0..70.4, |y| <= 40 m), as on KITTI's FOV-cropped clouds; for 360-degree frames "
    "such as dali synth's.",
)
@click.option("--class", "class_name", default="Car", show_default=True, help="Class to evaluate.")
@click.option(
    "--min-gt-points",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="Ignore ground-truth boxes with fewer points (needs num_points).",
)
@click.option(
    "--out", type=click.Path(dir_okay=False, path_type=Path), help="Write metrics.json here."
)
@device_options
@workers_option("1")
@executor_options
@click.option(
    "--save-predictions/--no-save-predictions",
    default=True,
    show_default=True,
    help="With --model and --out: also write the predictions (all scores) as "
    "predictions.parquet beside metrics.json (read by `dali report` for size plots).",
)
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
    out,
    workers,
    executor,
    ray_address,
    save_predictions,
    device,
    precision,
):
    """Average precision (KITTI protocol, BEV and 3D, float64 rotated IoU) of predictions.
    With --model, the detector runs on --executor with --workers."""
    from dali_cli.evaluate import EvaluationError, evaluate, format_table
    from dali_cli.executors import make_executor

    engine = make_executor(executor, workers, ray_address)

    for iou in ious:
        if not 0.0 <= iou < 1.0:
            raise click.BadParameter(f"must be in [0, 1), got {iou}", param_hint="--iou")
    if len(set(ious)) != len(ious):
        raise click.BadParameter(f"repeated threshold in {list(ious)}", param_hint="--iou")
    if out is not None:  # before any work: an --out dali must not write fails at once
        from dali_cli.output_paths import check_metrics_output

        check_metrics_output(
            out,
            {"model": model, "data": data, "pred": pred_path, "gt": gt_path, "scale": scale_from},
        )
    frame_ids = None
    source: dict = {}
    if model is not None or data is not None:
        if model is None or data is None:
            raise click.UsageError("--model and --data go together")
        if pred_path is not None:
            raise click.UsageError("give either --pred or --model/--data, not both")
        from dali_cli.device import inference_device, inference_runtime

        torch_device = inference_device(device, precision)  # a missing GPU: error, no output
        chosen_scale = _read_scale(scale, scale_from)
        frame_ids = FrameSet(data).frame_ids
        if gt_path is None:
            gt_path = Path(data)
        pred = _predict(model, data, chosen_scale, engine, out, torch_device, precision)
        source = {"model": str(model), "data": str(data), "scale": chosen_scale}
        runtime = {**inference_runtime(torch_device), "precision": precision}
    else:
        if scale is not None or scale_from is not None:
            raise click.UsageError("--scale/--scale-from only apply with --model")
        if pred_path is None or gt_path is None:
            raise click.UsageError("give --pred and --gt (or --model and --data)")
        pred, _ = _read_table(pred_path, "pred")
        source = {"pred": str(pred_path)}
    gt, label_frames = _read_table(gt_path, "gt")
    source["gt"] = str(gt_path)
    if frame_ids is None:
        frame_ids = label_frames
    metrics: dict = {}
    for index, iou in enumerate(ious):
        try:
            result = evaluate(
                pred,
                gt,
                iou=iou,
                recall_positions=int(recall_positions),
                protocol=protocol,
                class_name=class_name,
                min_gt_points=min_gt_points,
                frame_ids=frame_ids,
                front_only=front_only,
            )
        except EvaluationError as error:
            raise click.ClickException(
                f"cannot evaluate {source.get('pred', model)} against {gt_path}: {error}"
            ) from None
        block = result[class_name]
        block["source"] = source
        metrics[class_name if index == 0 else f"{class_name}@{iou:g}"] = block
    click.echo(format_table(metrics))
    metrics["sizes"] = {
        "pred": mean_box_size(pred, class_name, score_min=size_score_min),
        "gt": mean_box_size(gt, class_name),
    }
    if "scale" in source:
        metrics["scale"] = source["scale"]
    if model is not None:
        metrics["runtime"] = runtime
    if out is not None:
        if save_predictions and model is not None:
            _write_predictions(out.parent / PREDICTIONS_NAME, pred)
        _write_json(out, metrics)
        click.echo(f"wrote {out}", err=True)


PREDICTIONS_NAME = "predictions.parquet"


def _write_predictions(path: Path, pred: BoxTable) -> None:
    """The evaluated predictions as a box table file, written atomically."""
    import pyarrow.parquet as pq

    _write_atomically(
        path, lambda partial: pq.write_table(pred.to_arrow(), partial, compression="zstd")
    )


def mean_box_size(table: BoxTable, class_name: str, score_min: float | None = None):
    """Mean [l, w, h] in metres of the table's `class_name` boxes (score >= score_min), or None."""
    keep = np.asarray(table["label"]) == class_name
    if score_min is not None:
        keep &= np.asarray(table["score"]) >= score_min
    if not keep.any():
        return None
    lwh = table.boxes[keep, 3:6]
    return [round(float(v), 4) for v in lwh.mean(axis=0)]
