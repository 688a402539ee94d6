"""Stage ptsn_sweep: read a model and a target frame set (never its labels), find ŝ, write
sweep.parquet (every evaluated scale), scale.json (ŝ and how it was found), detections.parquet
(every box at the scales evaluated on all frames: `dali_cli.ptsn.detections`, for E_pred over a
stricter score cut at eval time), optional sweep.png."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Unpack

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from dali_cli import ptsn
from dali_cli.labels import SCORE_MIN
from dali_cli.ptsn import detections
from dali_cli.runtime import console
from dali_cli.runtime.device import InferenceOptions, inference_runtime, inference_setup, place
from dali_cli.runtime.errors import ParameterError, StageError
from dali_cli.sensors import get_profile
from dali_cli.store.artifacts import FrameSet
from dali_cli.store.manifest import BuildResult, StageOutcome, run_stage
from dali_cli.store.model_card import ModelCard, read_card
from dali_cli.store.scale_file import write_scale

STAGE = "ptsn_sweep"
SWEEP_NAME = "sweep.parquet"
PLOT_NAME = "sweep.png"


def load_detector(model_dir: str | Path) -> ptsn.Predictor:
    """The trained detector of `model_dir` (imported lazily: torch loads only when needed)."""
    from dali_cli.detector import Detector

    return Detector.load(model_dir)


def read_model_card(model_dir: str | Path) -> ModelCard:
    """The model card of `model_dir` (an empty card when it has no model.json: test doubles)."""
    if not (Path(model_dir) / "model.json").is_file():
        return ModelCard()
    return read_card(model_dir)


def resolve_e_est(
    spec: str,
    *,
    target_profile: str | None,
    card: ModelCard,
    source_profile: str | None,
    ros_factor: float | None,
    sensors_path: str | None,
) -> tuple[np.ndarray, dict]:
    """E_est (3,) and a record of where it came from. spec: sn | ros | L,W,H."""
    if spec == "sn":
        if not target_profile:
            raise ParameterError(
                ("expected_size", "target_profile"),
                "E_est sn needs the target's sensor profile: the frame set names none; name it",
            )
        lwh = np.asarray(get_profile(target_profile, sensors_path).car_mean_lwh_m)
        return lwh, {"mode": "sn", "profile": target_profile}
    if spec == "ros":
        factor = ros_factor if ros_factor is not None else card.ros_factor
        factor = ptsn.DEFAULT_ROS_FACTOR if factor is None else factor
        measured = card.source_mean_lwh_m
        if source_profile is None and measured is not None:
            record = {"mode": "ros", "source": "model card source_mean_lwh_m", "ros_factor": factor}
            return ptsn.ros_expected_size(list(measured), factor), record
        profile = source_profile or card.source_sensor
        if not profile:
            raise ParameterError(
                "expected_size",
                "E_est ros needs the source's sensor profile (model.json names none): give E_est "
                "as L,W,H",
            )
        source_lwh = get_profile(profile, sensors_path).car_mean_lwh_m
        lwh = ptsn.ros_expected_size(source_lwh, factor)
        return lwh, {"mode": "ros", "source_profile": profile, "ros_factor": factor}
    from dali_cli.quantities import CAR_SIZE_M, QuantityError, check_triple

    try:
        lwh = np.asarray(ptsn.parse_size(spec))
        check_triple(CAR_SIZE_M, [float(v) for v in lwh], "E_est")  # --target-size 1e308,1,1
    except (ValueError, QuantityError) as error:
        raise ParameterError("expected_size", str(error)) from None
    return lwh, {"mode": "explicit"}


class FrameStore:
    """`frames[i]`: frame i of a FrameSet, cropped to what any swept scale can bring into range.

    Frames are kept in memory up to `budget_bytes`; the rest are read again when needed.
    """

    def __init__(self, frameset: FrameSet, crop, budget_bytes: int = 2 << 30):
        self.frameset = frameset
        self.crop = crop
        self.budget_bytes = budget_bytes
        self.kept: dict[int, np.ndarray] = {}
        self.kept_bytes = 0

    def keep(self, index: int, points: np.ndarray) -> np.ndarray:
        points = self.crop(points)
        if self.kept_bytes + points.nbytes <= self.budget_bytes:
            self.kept[int(index)] = points
            self.kept_bytes += points.nbytes
        return points

    def __getitem__(self, index: int) -> np.ndarray:
        index = int(index)
        if index in self.kept:
            return self.kept[index]
        return self.crop(self.frameset.frame(index))

    def __len__(self) -> int:
        return len(self.frameset)


def _progress_bar(enabled: bool, description: str):
    from tqdm import tqdm

    return tqdm(desc=description, unit="frame", file=sys.stderr, disable=not enabled, leave=False)


def ptsn_sweep(
    model_dir: str | Path,
    target_dir: str | Path,
    out: str | Path,
    *,
    scale_range: ptsn.ScaleRange = ptsn.ScaleRange(0.8, 1.4, 0.01),
    expected_size: str = "sn",
    search: str = "bracket",
    frames: int | None = None,
    frame_fraction: float | None = None,
    score_min: float = SCORE_MIN,
    mean: str = "per-frame",
    match: str = "volume",
    seed: int = 0,
    subsample_fraction: float = 0.25,
    subsample_min: int = 16,
    noise: float = 0.02,
    no_detections: str = "identity",
    target_profile: str | None = None,
    source_profile: str | None = None,
    ros_factor: float | None = None,
    mount_height_m: float | None = None,
    plot: bool = False,
    sensors_path: str | None = None,
    force: bool = False,
    dry_run: bool = False,
    **inference: Unpack[InferenceOptions],
) -> StageOutcome:
    """Run the PTSN sweep stage (see the module docstring); `inference`: device, precision,
    batch size, progress and (tests) the detector loader (dali_cli.runtime.device.InferenceOptions)."""
    model_dir, target_dir = Path(model_dir), Path(target_dir)
    torch_device, precision = inference_setup(inference, "ptsn_sweep")
    if frames is not None and frame_fraction is not None:
        raise ParameterError(("frames", "frame_fraction"), "give one of the two, not both")
    if frames is None and frame_fraction is None:
        frames = ptsn.FRAME_CAP  # recorded as such: a sweep of every frame is another output
    if not model_dir.is_dir():
        raise StageError(f"{model_dir}: model directory not found")
    target = FrameSet(target_dir)
    target_profile = target_profile or target.sensor or None
    e_est, expected_record = resolve_e_est(
        expected_size, target_profile=target_profile, card=read_model_card(model_dir),
        source_profile=source_profile, ros_factor=ros_factor, sensors_path=sensors_path,
    )  # fmt: skip
    if mount_height_m is None:
        mount_height_m = profile_mount_height(target_profile, target_dir, sensors_path)
    params = {
        "scales": scale_range.as_list(), "expected_size": expected_size,
        "expected_lwh_m": [round(float(v), 6) for v in e_est], "search": search,
        "frames": frames, "frame_fraction": frame_fraction, "score_min": score_min, "mean": mean,
        "match": match, "seed": seed, "subsample_fraction": subsample_fraction,
        "subsample_min": subsample_min, "noise": noise, "target_profile": target_profile,
        "mount_height_m": mount_height_m, "plot": plot,
    }  # fmt: skip
    # recorded only when not the default: outputs of sweeps that found detections do not
    # depend on no_detections, and fp32 is the default precision: an option whose default
    # changes nothing leaves the parameters, and so existing sweeps' up-to-date check, as they are
    params.update(
        {"no_detections": no_detections} if no_detections != "identity" else {},
        **({"precision": precision} if precision != "fp32" else {}),
    )

    def build(directory: Path) -> BuildResult:
        loader = inference.get("detector_loader") or load_detector
        detector = place(loader(model_dir), torch_device, precision)
        return run_sweep(
            directory, detector, target, scale_range, e_est, expected_record, params,
            no_detections=no_detections, batch_size=inference.get("batch_size", 8),
            progress=inference.get("progress", True),
            torch_device=torch_device,
        )  # fmt: skip

    return run_stage(
        STAGE,
        out,
        inputs={"model": model_dir, "target": target_dir},
        params=params,
        build=build,
        force=force,
        dry_run=dry_run,
        seed=seed,
    )


def run_sweep(
    directory: Path,
    detector,
    target: FrameSet,
    scale_range: ptsn.ScaleRange,
    e_est: np.ndarray,
    expected_record: dict,
    params: dict,
    *,
    no_detections: str,
    batch_size: int,
    progress: bool,
    torch_device,
) -> BuildResult:
    """The sweep with the stage's `params` (frames, search, match, mean, seed, subsample,
    noise, score cut, pivot, plot): find ŝ on the selected frames, write sweep.parquet,
    scale.json (and sweep.png), and return the manifest's record."""
    selected = ptsn.select_frames(
        len(target), params["frames"], params["frame_fraction"], params["seed"]
    )
    store, usable = cropped_frames(target, selected, detector, scale_range)
    skipped = int(len(selected) - len(usable))
    subsample = ptsn.subsample_for_bracket(
        usable, params["subsample_fraction"], params["subsample_min"], params["seed"]
    )
    bar = _progress_bar(progress, "ptsn detector passes")
    cache = ptsn.DetectionCache(
        detector, store, score_min=params["score_min"], mount_height_m=params["mount_height_m"],
        batch_size=batch_size, progress=bar.update,
    )  # fmt: skip
    search, match = params["search"], params["match"]
    try:
        result = ptsn.find_scale(
            cache, scale_range, e_est, usable, search=search, match=match, mean=params["mean"],
            subsample=subsample, noise=params["noise"], no_detections=no_detections,
        )  # fmt: skip
    except ptsn.PTSNError as error:
        raise StageError(f"{target.directory}: {error}") from None
    finally:
        bar.close()
    rows = [evaluation.row() for evaluation in result.evaluations]
    pq.write_table(pa.Table.from_pylist(rows), directory / SWEEP_NAME)
    scales = detections.all_frame_scales(result.evaluations)  # cached: no detector pass
    kept = detections.detection_columns(cache, scales, usable)
    pq.write_table(pa.table(kept), directory / detections.DETECTIONS_NAME)
    document = scale_document(
        result, e_est, expected_record, cache,
        frames_selected=len(selected), frames_used=len(usable), frames_skipped=skipped,
        subsample=len(subsample) if search == "bracket" else len(usable), params=params,
        grid_frame_passes=len(scale_range.grid()) * len(usable),
    )  # fmt: skip
    write_scale(directory, document)
    if params["plot"]:
        from dali_cli.reporting.plots import plot_sweep

        title = f"PTSN sweep: ŝ = {result.scale:.3f} ({search}, {match})"
        plot_sweep(rows, result.scale, e_est, directory / PLOT_NAME, title)
    report_sweep(result, document, skipped, len(selected))
    return sweep_result(result, document, cache, torch_device)


def profile_mount_height(target_profile: str | None, target_dir: Path, sensors_path) -> float:
    """The target profile's mount height (m): the pivot the frames are scaled about."""
    if not target_profile:
        raise ParameterError(
            "target_profile", f"{target_dir}: the frame set names no sensor; name its profile"
        )
    return get_profile(target_profile, sensors_path).mount_height_m


def cropped_frames(target: FrameSet, selected: np.ndarray, detector, scale_range):
    """The selected frames cropped to what some swept scale brings into the detector's range
    (kept in memory, FrameStore), and the selected frame indices that have such points."""
    visible = getattr(detector, "visible_range", None)  # test doubles may see everything
    store = FrameStore(
        target, lambda p: ptsn.crop_for_scales(p, visible, scale_range.low, scale_range.high)
    )
    counts = np.zeros(len(selected), dtype=np.int64)  # points some swept scale brings in range
    for k, (_, points) in enumerate(target.iter_frames(selected)):
        counts[k] = len(store.keep(selected[k], points))
    return store, selected[counts > 0]


def report_sweep(result: ptsn.SearchResult, document: dict, skipped: int, selected: int) -> None:
    """The search's warnings, the skipped frames and the one-line summary."""
    for message in result.warnings:
        console.warn(message)
    if skipped:
        console.warn(f"{skipped} of {selected} selected frames have no points in range: skipped")
    print_summary(document)


def sweep_result(result: ptsn.SearchResult, document: dict, cache, torch_device) -> BuildResult:
    """The manifest's counts, timings, notes and the ŝ record of a sweep."""
    return BuildResult(
        counts={
            "frames": document["frames"]["used"],
            "frames_skipped": document["frames"]["skipped_no_points"],
            "scales_evaluated": document["passes"],
            "detector_frames": cache.frame_passes,
        },
        timings={"detector_seconds": round(cache.seconds, 3)},
        notes=list(result.warnings),
        extra={
            "ptsn": {"scale": result.scale, "clipped": result.clipped},
            "runtime": inference_runtime(torch_device),
        },
    )


def scale_document(
    result: ptsn.SearchResult,
    e_est: np.ndarray,
    expected_record: dict,
    cache: ptsn.DetectionCache,
    *,
    frames_selected: int,
    frames_used: int,
    frames_skipped: int,
    subsample: int,
    params: dict,
    grid_frame_passes: int,
) -> dict:
    """The content of scale.json (`"scale"` is the key other stages read)."""
    e_pred = np.asarray(result.mean_lwh, np.float64)

    def listed(values) -> list[float | None]:
        return [round(float(v), 6) if math.isfinite(v) else None for v in values]

    return {
        "scale": float(result.scale),  # exact: pseudo-label runs at the ŝ found
        "E_est": listed(e_est),
        "E_est_volume": round(float(np.prod(e_est)), 6),
        "expected_size": expected_record,
        "E_pred_at_scale": listed(e_pred),
        "E_pred": listed(e_pred),  # alias read by `dali report`
        "bias_lwh": listed(e_pred - e_est),
        "search": result.strategy,
        "match": params["match"],
        "mean": params["mean"],
        "fallback": result.fallback,
        "monotone": result.monotone,
        "clipped": result.clipped,
        "scale_range": params["scales"],
        "score_min": params["score_min"],
        "passes": len({(e.scale, e.subset) for e in result.evaluations}),
        "scales_evaluated": sorted({e.scale for e in result.evaluations}),
        "detector_frames": cache.frame_passes,
        "grid_detector_frames": grid_frame_passes,
        "detector_seconds": round(cache.seconds, 3),
        "frames": {
            "selected": frames_selected,
            "used": frames_used,
            "skipped_no_points": frames_skipped,
            "subsample": subsample,
        },
        "mount_height_m": params["mount_height_m"],
        "warnings": result.warnings,
    }


def print_summary(document: dict) -> None:
    e_est = ", ".join(f"{v:.2f}" for v in document["E_est"])
    e_pred = ", ".join("nan" if v is None else f"{v:.2f}" for v in document["E_pred_at_scale"])
    console.echo(
        f"ptsn-sweep: ŝ = {document['scale']:.4f} ({document['search']}, match {document['match']}"
        f"{', ' + document['fallback'] if document['fallback'] else ''}); "
        f"E_est = ({e_est}) m, E_pred(ŝ) = ({e_pred}) m; "
        f"{document['passes']} scale passes, {document['detector_frames']} detector frames "
        f"(full grid: {document['grid_detector_frames']})"
    )
