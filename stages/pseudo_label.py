"""Stage pseudo_label: run the detector on the target at the PTSN scale ŝ, de-scale, drop
implausible boxes (dali_cli.labels.plausibility, counted), keep score >= score_min, BEV NMS, remove the
remaining per-dimension size bias against E_est (`dali_cli.labels.size_correction`, on by default),
move each box onto its points (`dali_cli.labels.box_fit`, on by default), count the
original points in each box; write boxes.parquet, scale.json (the ScaleResult the
labels were made at: ŝ stored once, exactly as found) and summary.json (boxes per frame, mean
size vs E_est, score histogram)."""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Unpack

import numpy as np

from dali_cli import ptsn
from dali_cli.executors import make_executor, run_on
from dali_cli.labels import SCORE_MIN, box_fit, size_correction
from dali_cli.labels.pseudo_labeler import FrameLabeler, label_frame  # noqa: F401 (public here)
from dali_cli.runtime import console
from dali_cli.runtime.device import InferenceOptions, inference_runtime, inference_setup
from dali_cli.runtime.errors import ParameterError, StageError
from dali_cli.sensors import get_profile
from dali_cli.store.artifacts import BOX_FIELDS, BoxTable, FrameSet, write_boxes
from dali_cli.store.manifest import BuildResult, StageOutcome, run_stage
from dali_cli.store.scale_file import ScaleResult, read_scale, write_scale

STAGE = "pseudo_label"
SUMMARY_NAME = "summary.json"
SCORE_BINS = np.round(np.linspace(0.0, 1.0, 11), 2)  # histogram edges (11,)


def load_detector(model_dir: str | Path) -> ptsn.Predictor:
    """The trained detector of `model_dir` (torch is imported only here)."""
    from dali_cli.detector import Detector

    return Detector.load(model_dir)


def summarize(table: BoxTable, frames: int, e_est: list | None) -> dict:
    """summary.json: counts, mean size (per-frame mean as paper Eq. 1, and pooled) vs E_est."""
    sizes = table.boxes[:, 3:6]  # (N, 3)
    per_frame = ptsn.expected_prediction(
        [sizes[rows] for rows in table.rows_by_frame().values()], "per-frame"
    )
    pooled = sizes.mean(axis=0) if len(sizes) else np.full(3, np.nan)
    histogram, _ = np.histogram(table["score"], bins=SCORE_BINS)

    def listed(values) -> list[float | None]:
        return [round(float(v), 4) if math.isfinite(v) else None for v in values]

    summary = {
        "frames": frames,
        "frames_with_boxes": per_frame.frames_with_boxes,
        "boxes": len(table),
        "boxes_per_frame": round(len(table) / frames, 4) if frames else 0.0,
        "mean_lwh": listed(per_frame.mean_lwh),
        "mean_lwh_pooled": listed(pooled),
        "E_est": e_est,
        "mean_minus_E_est": None,
        "score_histogram": {"edges": SCORE_BINS.tolist(), "counts": histogram.tolist()},
        "num_points": {
            "median": float(np.median(table["num_points"])) if len(table) else None,
            "boxes_under_3": int(np.count_nonzero(table["num_points"] < 3)),
            "boxes_300_or_more": int(np.count_nonzero(table["num_points"] >= 300)),
        },
    }
    if e_est is not None and np.isfinite(per_frame.mean_lwh).all():
        summary["mean_minus_E_est"] = listed(per_frame.mean_lwh - np.asarray(e_est, np.float64))
    return summary


def pseudo_label(
    model_dir: str | Path,
    target_dir: str | Path,
    out: str | Path,
    *,
    scale: float | None = None,
    scale_from: str | Path | None = None,
    score_min: float = SCORE_MIN,
    nms_iou: float = 0.1,
    target_profile: str | None = None,
    mount_height_m: float | None = None,
    sensors_path: str | None = None,
    size_correction_method: str = "per-dim",
    point_fit: box_fit.PointFit | None = box_fit.PointFit(),
    force: bool = False,
    dry_run: bool = False,
    workers: int | None = None,
    executor: str = "local",
    ray_address: str | None = None,
    **inference: Unpack[InferenceOptions],
) -> StageOutcome:
    """Run the pseudo-label stage (see the module docstring). `point_fit`: move each box
    onto its points after the size correction (default: the standard fit; None: off).
    `executor`, `workers`, `ray_address`: the engine of the detector runs (dali_cli.executors);
    `inference`: device, precision, batch size, progress and (tests) the detector loader
    (InferenceOptions)."""
    model_dir, target_dir = Path(model_dir), Path(target_dir)
    torch_device, precision = inference_setup(inference, "pseudo_label")
    used, scale_source = used_scale(model_dir, scale, scale_from)
    e_est = list(used.e_est) if used.e_est is not None else None
    if mount_height_m is None and used.pivot_m is not None:
        mount_height_m = used.pivot_m  # scale about the very point the sweep scaled about
    target = FrameSet(target_dir)
    target_profile, mount_height_m, max_range_m = target_scaling(
        target, target_profile, mount_height_m, sensors_path
    )
    run = LabelRun(
        labeler=FrameLabeler(
            str(model_dir), str(target_dir), used.scale, mount_height_m, max_range_m,
            score_min, nms_iou,
            inference.get("batch_size", 8), inference.get("detector_loader") or load_detector,
            device=torch_device, precision=precision,
        ),
        target=target, used=used, scale_source=scale_source, mount_height_m=mount_height_m,
        method=correction_method(size_correction_method, e_est),
        requested_method=size_correction_method, e_est=e_est, score_min=score_min,
        point_fit=point_fit, device=torch_device, progress=inference.get("progress", True),
    )  # fmt: skip
    params = {
        "scale": used.scale, "score_min": score_min, "nms_iou": nms_iou,
        "target_profile": target_profile, "mount_height_m": mount_height_m,
        "size_correction": run.method,
        # recorded only when not the default: an option whose default changes nothing leaves
        # the parameters, and so the up-to-date check of every existing artifact, as they are
        **({"precision": precision} if precision != "fp32" else {}),
        **({"fit_points": point_fit.record()} if point_fit is not None else {}),
    }  # fmt: skip
    inputs = {"model": model_dir, "target": target_dir}
    inputs.update({"scale_from": scale_from} if scale_from is not None else {})
    engine = make_executor(executor, workers, ray_address)

    def build(directory: Path) -> BuildResult:
        return run_on(engine, "pseudo-label", lambda pool: build_labels(run, pool, directory))

    return run_stage(
        STAGE, out, inputs=inputs, params=params, build=build, force=force, dry_run=dry_run
    )


@dataclass(frozen=True)
class LabelRun:
    """What one pseudo-label build works with, resolved from the stage's options: the frame
    labeler (detector at ŝ, cut, NMS), the target, the scale it was found at and where, the
    size correction in effect (`method`; `requested_method` the option's) and the point fit."""

    labeler: FrameLabeler
    target: FrameSet
    used: ScaleResult
    scale_source: str
    mount_height_m: float | None
    method: str
    requested_method: str
    e_est: list | None
    score_min: float
    point_fit: box_fit.PointFit | None
    device: object
    progress: bool


def build_labels(run: LabelRun, pool, directory: Path) -> BuildResult:
    """Label the target on the executor `pool`, correct sizes, fit boxes to their points and
    write the artifact's files into `directory`; the stage's counts, timings and notes."""
    table, implausible, seconds = label_frames(
        run.labeler, pool, directory, run.target, run.progress
    )
    correction = fitted = None
    if run.method != "none" and len(table):
        table, correction = correct_table(table, run.e_est, run.score_min)
    if correction is not None or run.point_fit is not None:  # boxes changed: one more pass
        table, fitted = place_on_points(table, run.target, run.point_fit)
    fits = {"point_fit": fitted} if fitted is not None else {}
    write_outputs(
        directory, table,
        scale_record(run.used, run.scale_source, run.mount_height_m),
        summarize(table, len(run.target), run.e_est),
        {"boxes_implausible": implausible, "size_correction": correction, **fits},
    )  # fmt: skip
    return BuildResult(
        counts={"frames": len(run.target), "boxes": len(table), "boxes_implausible": implausible},
        timings={"detector_seconds": round(seconds, 3)},
        notes=pseudo_label_notes(
            implausible, run.method != run.requested_method, len(table), run.score_min
        ),
        extra={
            "pseudo_label": {"scale_source": run.scale_source},
            "runtime": inference_runtime(run.device),
            "size_correction": correction or {"method": run.method},
            **fits,
            "executor": pool.report(),
        },
    )


def target_scaling(
    target: FrameSet, target_profile: str | None, mount_height_m: float | None, sensors_path
) -> tuple[str | None, float | None, float | None]:
    """(profile name, pivot mount height in m, max range in m) of the target: the profile given
    or the frame set's, the pivot given or the profile's."""
    target_profile = target_profile or target.sensor or None
    profile = get_profile(target_profile, sensors_path) if target_profile else None
    if mount_height_m is None and profile is not None:
        mount_height_m = profile.mount_height_m
    return target_profile, mount_height_m, profile.max_range_m if profile is not None else None


def write_outputs(
    directory: Path, table: BoxTable, scale_document: dict, summary: dict, extra: dict
) -> None:
    """boxes.parquet, scale.json (ŝ, once) and summary.json (+ `extra`) into `directory`; the
    summary's line on the console."""
    write_boxes(directory, table)
    write_scale(directory, scale_document)
    summary = {**summary, "scale_source": scale_document["scale_source"], **extra}
    (directory / SUMMARY_NAME).write_text(json.dumps(summary, indent=2) + "\n")
    print_summary(summary, scale_document["scale"])


def used_scale(
    model_dir: Path, scale: float | None, scale_from: str | Path | None
) -> tuple[ScaleResult, str]:
    """The ScaleResult the pseudo labels are made at, and where its ŝ comes from: scale_from's
    scale.json exactly as the sweep wrote it, its ŝ replaced by `scale` when that is given
    ("option"; E_est and the pivot still from scale_from when given). Neither given is a
    ParameterError, a missing `model_dir` a StageError (checked before the scale file)."""
    if scale is None and scale_from is None:
        raise ParameterError(
            ("scale_from", "scale"), "give a ptsn-sweep output (its scale.json) or a scale"
        )
    if not model_dir.is_dir():
        raise StageError(f"{model_dir}: model directory not found")
    found = read_scale(scale_from) if scale_from is not None else None
    if scale is None:
        return found, str(scale_from)
    if found is None:
        return ScaleResult(scale=scale, record={"scale": scale}), "option"
    return replace(found, scale=scale, record={**found.record, "scale": scale}), "option"


def scale_record(used: ScaleResult, scale_source: str, mount_height_m: float | None) -> dict:
    """OUT/scale.json of the pseudo labels: the ScaleResult they were made at (the sweep's
    record, ŝ exact), where ŝ came from and the pivot the target was scaled about. The one
    place a pseudo-label output stores ŝ (read by self-train through read_scale)."""
    return {**used.record, "scale_source": scale_source, "mount_height_m": mount_height_m}


def correction_method(method: str, e_est: list | None) -> str:
    """The size correction to apply: `method`, or none when there is no E_est to correct
    towards (--scale without a sweep); an unknown method is a ParameterError."""
    if method not in size_correction.METHODS:
        raise ParameterError(
            "size_correction_method",
            f"must be one of {', '.join(size_correction.METHODS)}, got '{method}'",
        )
    return "none" if e_est is None else method


def label_frames(
    labeler: FrameLabeler, pool, directory: Path, target: FrameSet, progress: bool
) -> tuple[BoxTable, int, float]:
    """Every target frame's pseudo boxes as one table (ŝ is not a column: OUT/scale.json holds
    it once), the count of
    boxes above the score cut dropped as implausible, and the detector's seconds."""
    from tqdm import tqdm

    ids, boxes_all, scores_all, counts_all = [], [], [], []
    bar = tqdm(
        total=len(target), desc="pseudo-label", unit="frame", file=sys.stderr,
        disable=not progress, leave=False,
    )  # fmt: skip
    seconds = 0.0
    implausible = 0  # boxes above the score cut dropped as implausible
    for labels in labeler.frame_labels(pool, directory, target):
        ids.extend([labels.frame_id] * len(labels.boxes))
        boxes_all.append(labels.boxes)
        scores_all.append(labels.scores)
        counts_all.append(labels.counts)
        implausible += labels.implausible
        seconds += labels.seconds
        bar.update(1)
    bar.close()
    if not ids:
        return BoxTable.empty(), implausible, seconds
    table = BoxTable.from_arrays(
        np.asarray(ids),
        np.concatenate(boxes_all),
        score=np.concatenate(scores_all),
        num_points=np.concatenate(counts_all),
    )
    return table, implausible, seconds


def pseudo_label_notes(
    implausible: int, skipped_correction: bool, boxes: int, score_min: float
) -> list[str]:
    """The manifest's notes (each also a warning): implausible boxes dropped, size correction
    skipped, no boxes at all."""
    notes = []
    if implausible:
        notes.append(
            f"dropped {implausible} implausible boxes with score >= {score_min} (size or "
            "distance beyond dali_cli.labels.plausibility's limits)"
        )
        console.warn(notes[-1])
    if skipped_correction:
        notes.append("size correction skipped: no E_est (give --scale-from PTSN_DIR)")
        console.warn(notes[-1], colour="yellow", bold=False)
    if not boxes:
        notes.append(f"no boxes with score >= {score_min} on any frame")
        console.warn(notes[-1])
    return notes


def correct_table(table: BoxTable, e_est: list, score_min: float) -> tuple[BoxTable, dict]:
    """`table` with l, w, h corrected per dimension towards E_est (bottom faces kept; num_points
    as before: place_on_points recounts them); the correction's record."""
    boxes, record = size_correction.correct_sizes(
        table.boxes, table["score"], table.frame_id, e_est, score_min=score_min
    )
    corrected = BoxTable.from_arrays(
        table.frame_id,
        boxes,
        score=table["score"],
        num_points=table["num_points"],
        size_factor_l=np.full(len(table), record.factors[0]),
        size_factor_w=np.full(len(table), record.factors[1]),
        size_factor_h=np.full(len(table), record.factors[2]),
    )
    return corrected, record.to_dict()


def place_on_points(
    table: BoxTable, target: FrameSet, fit: box_fit.PointFit | None
) -> tuple[BoxTable, dict | None]:
    """One pass over the target frames: every box moved onto its frame's points when `fit` is
    given (dali_cli.labels.box_fit; sizes, z, scores and the other columns kept), and
    num_points recounted on the original points. Returns the table and the point fit's record
    (None without it: boxes fitted (enough points), mean shift (m) and turn (deg) over them)."""
    from dali_cli.geometry import count_points_in_boxes

    boxes, counts = table.boxes.copy(), np.asarray(table["num_points"]).copy()
    used = np.zeros(len(table), np.int64)
    rows = table.rows_by_frame()
    for frame_id, points in target.iter_frames():
        if frame_id in rows:
            r = rows[frame_id]
            if fit is not None:
                boxes[r], used[r] = box_fit.fit_boxes(table.boxes[r], points, fit)
            counts[r] = count_points_in_boxes(points, boxes[r])
    moved = table.with_columns(
        **{name: boxes[:, i] for i, name in enumerate(BOX_FIELDS)}, num_points=counts
    )
    return moved, point_fit_record(table, boxes, used, fit)


def point_fit_record(
    table: BoxTable, boxes: np.ndarray, used: np.ndarray, fit: box_fit.PointFit | None
) -> dict | None:
    """The point fit's record (place_on_points), None without a fit."""
    from dali_cli.geometry import wrap_angle

    if fit is None:
        return None
    fitted = used >= fit.min_points
    shift = np.hypot(*(boxes[:, :2] - table.boxes[:, :2]).T)
    turn = np.degrees(np.abs(wrap_angle(boxes[:, 6] - table.boxes[:, 6])))
    record = {
        "boxes_fitted": int(fitted.sum()),
        "boxes_too_few_points": int((~fitted).sum()),
        "mean_shift_m": round(float(shift[fitted].mean()), 4) if fitted.any() else 0.0,
        "mean_turn_deg": round(float(turn[fitted].mean()), 3) if fitted.any() else 0.0,
    }
    return record


def print_summary(summary: dict, scale: float) -> None:
    def triple(values) -> str:
        return (
            "—" if values is None else ", ".join("nan" if v is None else f"{v:.2f}" for v in values)
        )

    console.echo(
        f"pseudo-label: {summary['boxes']} boxes on {summary['frames']} frames "
        f"({summary['boxes_per_frame']:.2f}/frame) at s = {scale:.4f}; "
        f"mean l/w/h ({triple(summary['mean_lwh'])}) m vs E_est ({triple(summary['E_est'])}) m"
    )
    correction = summary.get("size_correction")
    if correction:
        console.echo(
            f"size correction (per dimension, target statistics only): factors "
            f"{triple(correction['factors_lwh'])}; mean l/w/h before "
            f"({triple(correction['mean_lwh_before'])}) m"
        )
    fitted = summary.get("point_fit")
    if fitted:
        console.echo(
            f"point fit: {fitted['boxes_fitted']} boxes fitted to their points (mean shift "
            f"{fitted['mean_shift_m']:.2f} m, turn {fitted['mean_turn_deg']:.1f} deg); "
            f"{fitted['boxes_too_few_points']} with too few points kept"
        )
