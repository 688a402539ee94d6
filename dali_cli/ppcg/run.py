"""The body of the ppcg-rc and ppcg-cf stages (`stages.ppcg_rc`, `stages.ppcg_cf`): read the target
frames, a box table and a model library; write the frames with each processed box's points replaced (frames.zarr), the boxes with
their PPCG outcome (boxes.parquet) and manifest.json (counts, per-frame timing).

boxes.parquet = the input rows (in order) plus ppcg (rc | cf | raw), ppcg_reason
(ok | dense | too_few_points | no_hits | label), points_before / points_after (the box's points
above its ground height, before / after), model_id ("" when raw); num_points becomes the
number of points in the box in the new frame (rows of other labels keep theirs). Rows of the
processed label outside dali_cli.labels.plausibility's limits are dropped, neither re-cast nor passed on
to retraining (manifest count dropped_implausible, a note naming the first).
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import TypedDict, Unpack

import numpy as np

from dali_cli.executors import make_executor, run_on
from dali_cli.labels import plausibility
from dali_cli.ppcg.cf import CfParams
from dali_cli.ppcg.driver import Job, run_frames
from dali_cli.ppcg.frame import DEFAULT_POINT_MARGIN_M
from dali_cli.ppcg.models import ModelBank
from dali_cli.ppcg.orient import turned
from dali_cli.ppcg.point_models import angular_threshold_rad
from dali_cli.ppcg.rc import RcParams
from dali_cli.runtime import console
from dali_cli.runtime.device import check_options
from dali_cli.runtime.errors import ParameterError, StageError
from dali_cli.sensors import get_profile
from dali_cli.store.artifacts import BoxTable, FrameSet, FrameSetWriter, read_boxes, write_boxes
from dali_cli.store.manifest import BuildResult, StageOutcome, check_made_from, run_stage
from dali_cli.world.cars import LABEL_SLACK_M


def resolve_orient(params: RcParams | CfParams, models: str) -> RcParams | CfParams:
    """`params` with `orient` decided: None (the stages' default) turns boxes round by their model
    with mesh models and not with point models (orient.flips needs meshes); True with point
    models is an error (ParameterError on orient_models)."""
    if params.orient is None:
        return dataclasses.replace(params, orient=models == "cad")
    if params.orient and models != "cad":
        raise ParameterError(
            "orient_models", "orienting boxes by their model needs mesh models (--models cad)"
        )
    return params


MAX_LABEL_SLACK_M = 0.5  # room a label leaves around its car, per face: more is not a car's label

NOTES = (
    "occlusion between objects is not modelled: each box is processed alone",
    "ground rule: a box's points below max(box bottom, -mount height) + ground_margin_m stay "
    "as they are and are not counted; generated points below that height are dropped",
)


def boxes_by_frame(
    table: BoxTable, frames: FrameSet, label: str | None, boxes_path: Path
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per target frame: the rows `(k_i,)` of `table` to process (table order) and their boxes
    `(k_i, 7)`. Errors name the box file, row, frame and field."""
    frame_ids = table.frame_id.astype(str)
    known = np.isin(frame_ids, np.asarray(frames.frame_ids, dtype=str))
    if not known.all():
        row = int(np.flatnonzero(~known)[0])
        raise StageError(
            f"{boxes_path}: row {row} frame '{frame_ids[row]}' is not in {frames.path}"
        )
    selected = np.ones(len(table), bool)
    if label is not None and len(table):
        selected = np.asarray(table["label"]).astype(str) == label
    boxes = table.boxes
    for column, name in ((3, "l"), (4, "w"), (5, "h")):
        bad = selected & ~(boxes[:, column] > 0)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise StageError(
                f"{boxes_path}: row {row} (frame '{frame_ids[row]}') field '{name}' must be > 0"
            )
    grouped = table.select(np.flatnonzero(selected)).rows_by_frame() if selected.any() else {}
    rows_in_table = np.flatnonzero(selected)
    rows, frame_boxes = [], []
    for frame_id in frames.frame_ids:
        local = grouped.get(frame_id, np.zeros(0, np.int64))
        rows.append(rows_in_table[local])
        frame_boxes.append(boxes[rows_in_table[local]])
    return rows, frame_boxes


def library_mesh_count(library_dir: Path) -> int:
    """Number of meshes of a library, from its index alone (no mesh is loaded)."""
    import pyarrow.parquet as pq

    from dali_cli.library import MESHES_INDEX, LibraryError

    path = Path(library_dir) / MESHES_INDEX
    try:
        return int(pq.read_metadata(path).num_rows)
    except (OSError, ValueError) as error:
        raise LibraryError(f"{path}: cannot read the library index ({error})") from None


def target_profile(frames: FrameSet, sensor: str | None, sensors_path: str | None):
    """(sensor name, SensorProfile) of the target: `sensor`, else the frame set's own."""
    name = sensor or frames.sensor
    if not name:
        raise ParameterError(
            "sensor", f"{frames.path}: no 'sensor' attribute; name the target's sensor"
        )
    return name, get_profile(name, sensors_path)


class PpcgOptions(TypedDict, total=False):
    """The keyword arguments ppcg-rc and ppcg-cf share besides their method's parameters."""

    sensor: str | None  # target sensor profile (default: the frame set's)
    sensors_path: str | None
    models: str | None  # cad | points (default: cad when the library has meshes)
    label: str | None  # boxes of this label are processed, the others pass through as raw
    workers: int | None
    force: bool
    dry_run: bool
    progress: bool
    bank: ModelBank | None  # replaces the library (tests)
    executor: str  # local | ray (dali_cli.executors)
    ray_address: str | None


class PpcgStageOptions(PpcgOptions, total=False):
    """PpcgOptions and the settings of the stage functions that ppcg-rc and ppcg-cf share
    (stages.ppcg_rc, stages.ppcg_cf; defaults in PPCG_STAGE_DEFAULTS)."""

    top_k: int  # pick at random among the K best models (per-box seed); 1 = the best
    seed: int
    ground_margin_m: float  # frame.ground_heights' margin (m)
    orient_models: bool | None  # turn a box round when its model fits better (None: meshes only)
    point_margin_m: float  # a box's points are those in the box grown by this (m)
    label_slack_m: tuple[float, float, float]  # (l, w, h) room a box leaves around its car (m)


PPCG_STAGE_DEFAULTS = {
    "top_k": 1,
    "seed": 0,
    "ground_margin_m": 0.1,
    "orient_models": None,
    "point_margin_m": DEFAULT_POINT_MARGIN_M,
    "label_slack_m": tuple(LABEL_SLACK_M),  # the synthetic world's labels
}


def run_ppcg_stage(
    mode: str,
    target_dir: str | Path,
    boxes_dir: str | Path,
    library_dir: str | Path,
    out: str | Path,
    *,
    method: dict,
    options: PpcgStageOptions,
) -> StageOutcome:
    """ppcg-rc or ppcg-cf from its stage function's arguments (stages.ppcg_rc, stages.ppcg_cf):
    `method` the mode's own parameters and, of `options`, top_k, seed and ground_margin_m (both
    recorded as given); the angular threshold (and RC's mount height) from the target's profile;
    run_ppcg checks the margin and the slack, resolves the orientation (it knows the model kind)
    and records each only when used."""
    check_options(options, PpcgStageOptions, f"ppcg_{mode}")
    options = dict(options)  # the caller's keywords stay as given
    stage = {name: options.pop(name, default) for name, default in PPCG_STAGE_DEFAULTS.items()}
    shared = {name: stage[name] for name in ("top_k", "seed", "ground_margin_m")}
    _, profile = target_profile(
        FrameSet(target_dir), options.get("sensor"), options.get("sensors_path")
    )
    params_class, of_profile = (
        (RcParams, {"mount_height_m": profile.mount_height_m}) if mode == "rc" else (CfParams, {})
    )
    params = params_class(
        **of_profile,
        theta_rad=angular_threshold_rad(profile.points_per_beam),
        orient=stage["orient_models"],
        point_margin_m=float(stage["point_margin_m"]),
        label_slack_m=tuple(float(v) for v in stage["label_slack_m"]),
        **method,
        **shared,
    )
    return run_ppcg(
        mode, target_dir, boxes_dir, library_dir, out,
        params=params, stage_params={**method, **shared}, **options,
    )  # fmt: skip


def run_ppcg(
    mode: str,
    target_dir: str | Path,
    boxes_dir: str | Path,
    library_dir: str | Path,
    out: str | Path,
    *,
    params: RcParams | CfParams,
    stage_params: dict,
    **options: Unpack[PpcgOptions],
) -> StageOutcome:
    """The shared body of ppcg-rc and ppcg-cf (mode "rc" or "cf"); `executor`, `workers`,
    `ray_address`: the engine of the per-frame work (dali_cli.executors)."""
    sensor, sensors_path = options.get("sensor"), options.get("sensors_path")
    label, bank = options.get("label", "Car"), options.get("bank")
    engine = make_executor(
        options.get("executor", "local"), options.get("workers", 1), options.get("ray_address")
    )
    target_dir, boxes_dir, library_dir = Path(target_dir), Path(boxes_dir), Path(library_dir)
    frames = FrameSet(target_dir)
    check_made_from(boxes_dir, "target", target_dir)  # pseudo boxes of this very frame set
    sensor, profile = target_profile(frames, sensor, sensors_path)
    models = model_kind(bank, options.get("models"), library_dir)
    if not params.point_margin_m >= 0:
        raise ParameterError("point_margin_m", f"must be >= 0 m, got {params.point_margin_m}")
    slack = np.asarray(params.label_slack_m, dtype=np.float64)
    if slack.shape != (3,) or not ((slack >= 0) & (slack <= MAX_LABEL_SLACK_M)).all():
        raise ParameterError(
            "label_slack_m", f"need 3 values (l, w, h) in [0, {MAX_LABEL_SLACK_M}] m, got {slack}"
        )
    params = resolve_orient(params, models)
    params_record = {
        **stage_params,
        # recorded only when used: outputs made without them stay up to date
        **({"orient": True} if params.orient else {}),
        **({"point_margin_m": params.point_margin_m} if params.point_margin_m else {}),
        "label_slack_m": slack.tolist(),
        "sensor": sensor,
        "models": models,
        "label": label,
        "theta_deg": float(np.degrees(angular_threshold_rad(profile.points_per_beam))),
        "profile": dataclasses.asdict(profile),  # a changed --sensors file makes the output stale
    }
    inputs = {"target": target_dir, "boxes": boxes_dir, "library": library_dir}
    job = Job(mode, str(target_dir), str(library_dir), models, sensor, sensors_path, params)

    def build(directory: Path) -> BuildResult:
        return run_on(engine, f"ppcg-{mode}", lambda pool: build_on(pool, directory))

    def build_on(pool, directory: Path) -> BuildResult:
        local_bank = bank
        if local_bank is None and pool.serial:  # loaded only when the stage runs in this process
            local_bank = load_bank(library_dir, models)
        table, implausible_note, implausible = read_ppcg_boxes(
            boxes_dir, label, profile.max_range_m
        )
        boxes_path = boxes_dir / "boxes.parquet" if boxes_dir.is_dir() else boxes_dir
        rows, frame_boxes = boxes_by_frame(table, frames, label, boxes_path)
        attrs = {k: v for k, v in frames.attrs.items() if k not in ("count", "frame_convention")}
        attrs.update({"sensor": frames.sensor or sensor, "ppcg": mode, "ppcg_models": models})
        outcomes = BoxOutcomes.start(table)
        tally = write_frames(
            directory, attrs, frames, rows,
            lambda: run_frames(job, frame_boxes, pool, local_bank, directory),
            outcomes, mode, options.get("progress", True),
        )  # fmt: skip
        write_boxes(directory, outcomes.table(table, params.orient))
        counts = ppcg_counts(mode, frames, rows, outcomes, implausible, tally)
        timings = ppcg_timings(frames, rows, tally)
        echo_summary(mode, counts, tally.wall)
        return BuildResult(
            counts=counts,
            timings=timings,
            notes=[*NOTES, *([implausible_note] if implausible_note else [])],
            extra={
                "per_frame_compute_seconds": [round(float(s), 6) for s in tally.seconds],
                "executor": pool.report(),
            },
        )

    return run_stage(
        f"ppcg_{mode}",
        out,
        inputs=inputs,
        params=params_record,
        build=build,
        force=options.get("force", False),
        dry_run=options.get("dry_run", False),
        seed=stage_params.get("seed"),
    )


def echo_summary(mode: str, counts: dict, wall: float) -> None:
    """The stage's one line: boxes replaced, frames, skips by reason, time per frame."""
    frames = counts["frames"]
    console.echo(
        f"ppcg-{mode}: {counts[f'boxes_{mode}']}/{counts['boxes']} boxes replaced on "
        f"{counts['frames_with_boxes']} of {frames} frames; skipped: "
        f"{counts['skipped_dense']} dense, {counts['skipped_too_few_points']} too few points, "
        f"{counts['skipped_no_hits']} no hits; {wall / max(frames, 1) * 1e3:.1f} ms/frame"
    )


def model_kind(bank: ModelBank | None, models: str | None, library_dir: Path) -> str:
    """The kind of models fitted: the bank's, else `models`, else cad when the library has
    meshes and points when it has none."""
    if bank is not None:
        return bank.kind
    if models is None:
        return "cad" if library_mesh_count(library_dir) else "points"
    return models


def load_bank(library_dir: Path, models: str) -> ModelBank:
    """The library's models of kind `models`, ready to fit (a bad library is a StageError)."""
    from dali_cli.library import read_library

    try:
        return ModelBank.from_library(read_library(library_dir), models, str(library_dir))
    except ValueError as error:
        raise StageError(str(error)) from None


def read_ppcg_boxes(boxes_dir: Path, label: str | None, max_range_m: float):
    """The box table to process; a row of `label` (all rows when None) with positive sizes but
    outside dali_cli.labels.plausibility's limits is an error naming the file, row, frame and
    field (non-positive sizes stay an error of boxes_by_frame). Returns (table, None, 0): no
    row is ever dropped silently."""
    table = read_boxes(boxes_dir)
    boxes_path = boxes_dir / "boxes.parquet" if boxes_dir.is_dir() else boxes_dir
    boxes = table.boxes
    selected = np.ones(len(table), bool)
    if label is not None and len(table):
        selected = np.asarray(table["label"]).astype(str) == label
    positive = (boxes[:, 3:6] > 0).all(axis=1)
    plausibility.refuse_implausible(
        boxes, selected & positive, str(boxes_path), table.frame_id, max_range_m
    )
    return table, None, 0


@dataclasses.dataclass
class BoxOutcomes:
    """Per row of the box table `(n,)`: its PPCG outcome (rc | cf | raw), the reason, the
    points above its ground before / after, the fitted model and the box's new point count."""

    ppcg: np.ndarray
    reason: np.ndarray
    before: np.ndarray
    after: np.ndarray
    model_id: np.ndarray
    num_points: np.ndarray
    flipped: np.ndarray

    @classmethod
    def start(cls, table: BoxTable) -> BoxOutcomes:
        """Every row raw (reason label) until its frame's result says otherwise."""
        count = len(table)
        return cls(
            ppcg=np.full(count, "raw", dtype=object),
            reason=np.full(count, "label", dtype=object),
            before=np.zeros(count, np.int32),
            after=np.zeros(count, np.int32),
            model_id=np.full(count, "", dtype=object),
            num_points=np.asarray(table["num_points"], np.int32).copy(),
            flipped=np.zeros(count, bool),
        )

    def record(self, frame_rows: np.ndarray, records) -> None:
        """The outcomes of one frame's processed rows (driver records, row order)."""
        self.ppcg[frame_rows] = records.ppcg
        self.reason[frame_rows] = records.reason
        self.before[frame_rows] = records.points_before
        self.after[frame_rows] = records.points_after
        self.model_id[frame_rows] = records.model_id
        self.num_points[frame_rows] = records.ground_points + records.points_after
        self.flipped[frame_rows] = records.flipped

    def table(self, table: BoxTable, orient: bool = False) -> BoxTable:
        """`table` with the outcome columns (boxes.parquet of the output); with `orient`, the
        turned boxes' yaw and a heading_flipped column."""
        if orient:
            table = table.with_columns(
                yaw=turned(table.boxes, self.flipped)[:, 6], heading_flipped=self.flipped
            )
        return table.with_columns(
            ppcg=self.ppcg,
            ppcg_reason=self.reason,
            points_before=self.before,
            points_after=self.after,
            model_id=self.model_id,
            num_points=self.num_points,
        )


@dataclasses.dataclass
class FrameTally:
    """What writing the frames measured."""

    seconds: np.ndarray
    """compute seconds per frame `(frames,)`"""
    points_in: int
    points_out: int
    """seconds of the whole loop: wall clock, CPU (all threads of this process), read, write"""
    wall: float
    cpu: float
    read_seconds: float
    write_seconds: float

    @classmethod
    def start(cls, frames: int) -> FrameTally:
        return cls(np.zeros(frames), 0, 0, 0.0, 0.0, 0.0, 0.0)


def write_frames(
    directory: Path,
    attrs: dict,
    frames: FrameSet,
    rows: list[np.ndarray],
    run,
    outcomes: BoxOutcomes,
    mode: str,
    progress: bool,
) -> FrameTally:
    """Write each frame's result of `run()` (the per-frame results in frame order, started once
    the output's frame writer is open) into directory/frames.zarr and record its boxes'
    outcomes; returns the loop's tally."""
    from tqdm import tqdm

    tally = FrameTally.start(len(frames))
    started, started_cpu = time.perf_counter(), time.process_time()
    bar = tqdm(
        total=len(frames), desc=f"ppcg-{mode}", unit="frame", file=sys.stderr,
        disable=not progress, leave=False,
    )  # fmt: skip
    # raw chunks: zstd saves ~8% on LiDAR coordinates at about the cost of the whole RC step
    with FrameSetWriter(directory, attrs.pop("sensor"), attrs, compress=False) as writer:
        for index, result in enumerate(run()):
            write_started = time.perf_counter()
            writer.append(result.frame_id, result.points)
            tally.write_seconds += time.perf_counter() - write_started
            tally.read_seconds += result.read_seconds
            outcomes.record(rows[index], result.records)
            tally.seconds[index] = result.seconds
            tally.points_in += int(frames.offsets[index + 1] - frames.offsets[index])
            tally.points_out += len(result.points)
            bar.update(1)
        close_started = time.perf_counter()
    tally.write_seconds += time.perf_counter() - close_started  # the last chunk and the index
    bar.close()
    tally.wall, tally.cpu = time.perf_counter() - started, time.process_time() - started_cpu
    return tally


def ppcg_counts(
    mode: str,
    frames: FrameSet,
    rows: list[np.ndarray],
    outcomes: BoxOutcomes,
    implausible: int,
    tally: FrameTally,
) -> dict:
    """The manifest's counts: frames with / without boxes, boxes processed and skipped by
    reason, points in and out."""
    processed = outcomes.reason != "label"
    reason = outcomes.reason
    return {
        "frames": len(frames),
        "frames_with_boxes": int(sum(len(r) > 0 for r in rows)),
        "frames_without_boxes": int(sum(len(r) == 0 for r in rows)),
        "boxes": int(processed.sum()),
        "boxes_other_label": int((~processed).sum()),
        f"boxes_{mode}": int((outcomes.ppcg == mode).sum()),
        "skipped_dense": int((reason == "dense").sum()),
        "skipped_too_few_points": int((reason == "too_few_points").sum()),
        "skipped_no_hits": int((reason == "no_hits").sum()),
        "dropped_implausible": implausible,
        "points_in": tally.points_in,
        "points_out": tally.points_out,
    }


def ppcg_timings(frames: FrameSet, rows: list[np.ndarray], tally: FrameTally) -> dict:
    """The manifest's timings: per frame (wall, CPU, read, compute, write) and the compute
    time of the frames with boxes (mean, median, p95, max)."""
    count = max(len(frames), 1)
    seconds = tally.seconds
    busy = seconds[[len(r) > 0 for r in rows]] if len(rows) else seconds
    return {
        "frames_seconds": round(tally.wall, 4),
        "seconds_per_frame": round(tally.wall / count, 6),
        "frames_cpu_seconds": round(tally.cpu, 4),  # all threads of this process (zarr I/O too)
        "cpu_seconds_per_frame": round(tally.cpu / count, 6),
        "read_seconds_per_frame": round(tally.read_seconds / count, 6),
        "compute_seconds_per_frame": round(float(seconds.sum()) / count, 6),
        "write_seconds_per_frame": round(tally.write_seconds / count, 6),
        "compute_seconds_per_frame_with_boxes": {
            "mean": round(float(busy.mean()), 6) if len(busy) else None,
            "median": round(float(np.median(busy)), 6) if len(busy) else None,
            "p95": round(float(np.percentile(busy, 95)), 6) if len(busy) else None,
            "max": round(float(busy.max()), 6) if len(busy) else None,
        },
    }
