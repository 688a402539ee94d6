"""Stage eval: KITTI-protocol AP_BEV / AP_3D of predictions against labels (dali_cli.evaluation.evaluate).

The predictions are a box table (or KITTI label directory), or come from running a model on a
frame set at a scale (1, or ŝ of a ptsn-sweep's scale.json) through the detector's one predict
loop (`dali_cli.detector.predict_frameset`). Output, either:
- an artifact directory (`out` not ending in .json; what the Makefile uses): OUT/metrics.json,
  OUT/predictions.parquet (model runs) and OUT/manifest.json under the stage contract (written
  atomically as a whole, skipped when inputs and parameters are unchanged); a KITTI-protocol
  OUT/metrics_kitti.json added later is not part of its content hash; or
- a metrics file (`out` ending in .json): FILE and predictions.parquet beside it, each atomic.
With `size_correction="per-dim"` the Car predictions are resized per dimension before they are
evaluated (and saved) by the factors E_est / E_pred(ŝ) of the `scale_from` sweep
(`dali_cli.labels.size_correction.factors_from_sweep`: label-free, from the unlabelled target training
frames), bottom face kept; metrics.json records them under
"size_correction". metrics.json's "errors" holds the error breakdown of the same boxes
(dali_cli.evaluation.errors); it is not a parameter, so artifacts written before it stay up to
date without it (`dali report` says to rerun with --force). It works on both routes: a model run at ŝ, or a prediction table (then
`scale_from` gives only the factors).
Returns the metrics for the command to print."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dali_cli.evaluation.evaluate import check_ious
from dali_cli.importers.kitti_label import read_box_source
from dali_cli.labels import SCORE_MIN, plausibility
from dali_cli.runtime import console
from dali_cli.runtime.errors import ParameterError, StageError
from dali_cli.store.artifacts import BOX_FIELDS, BoxTable, FrameSet
from dali_cli.store.atomic_file import write_atomically, write_text_atomically
from dali_cli.store.output_paths import DERIVED_FILES
from dali_cli.store.regular_files import read_json_file

PREDICTIONS_NAME = "predictions.parquet"
METRICS_NAME = "metrics.json"
ERRORS_KEY = "errors"  # metrics.json's error breakdown (dali_cli.evaluation.errors)
KITTI_METRICS_NAME = DERIVED_FILES["eval"][0]  # written beside metrics.json by a second eval


@dataclass
class EvalResult:
    """The metrics document (as written to metrics.json), the paths written and, for an
    artifact directory, what the stage runner did ("ran", "skipped", "dry-run")."""

    metrics: dict
    written: list[Path] = field(default_factory=list)
    status: str = "ran"


def resolve_scale(scale: float | None, scale_from: str | Path | None) -> float:
    """The inference scale: `scale`, ŝ of `scale_from`'s scale.json, or 1."""
    if scale is not None and scale_from is not None:
        raise ParameterError(("scale", "scale_from"), "give one of the two, not both")
    if scale_from is None:
        value = 1.0 if scale is None else scale
    else:
        from dali_cli.store.scale_file import read_scale

        value = read_scale(scale_from).scale
    if not value > 0:
        raise ParameterError("scale", f"the scale must be positive, got {value}")
    return float(value)


def predict(
    model, data, scale: float, device, precision: str, engine=None, near=None, progress=True,
    fusion=None,
) -> BoxTable:  # fmt: skip
    """Every prediction (all scores) of the model of `model` on the frame set `data`, on the
    torch `device` at `precision`, on `engine` (dali_cli.executors; None: this process); a
    parallel engine's shards go to a temporary folder in `near` (workers must see it);
    `progress`: a progress bar on stderr; `fusion`: a detector.fusion.TestTimeFusion or None."""
    import shutil
    import tempfile

    try:
        from dali_cli.detector import predict_frameset
    except ImportError as error:
        raise StageError(f"the detector is not available ({error})") from None
    from dali_cli.executors import run_on

    options = dict(
        scale=scale, score_min=0.0, progress=progress, device=device, precision=precision,
        fusion=fusion,
    )  # fmt: skip
    if engine is None or engine.serial:  # the reference path: in this process
        if engine is None:
            return predict_frameset(model, data, **options)
        return run_on(engine, "eval", lambda _: predict_frameset(model, data, **options))
    if near is not None:
        Path(near).mkdir(parents=True, exist_ok=True)
    where = Path(tempfile.mkdtemp(prefix=".dali-eval-shards-", dir=near))
    try:
        return run_on(
            engine,
            "eval",
            lambda pool: predict_frameset(model, data, executor=pool, shards_dir=where, **options),
        )
    finally:
        shutil.rmtree(where, ignore_errors=True)


def mean_box_size(table: BoxTable, class_name: str, score_min: float | None = None):
    """Mean [l, w, h] in metres of the table's `class_name` boxes (score >= score_min), or None."""
    keep = np.asarray(table["label"]) == class_name
    if score_min is not None:
        keep &= np.asarray(table["score"]) >= score_min
    if not keep.any():
        return None
    lwh = table.boxes[keep, 3:6]
    return [round(float(v), 4) for v in lwh.mean(axis=0)]


def check_size_correction(method: str, scale: float | None, scale_from) -> None:
    """ParameterError for an unknown method or a correction without a sweep to read it from."""
    from dali_cli.labels.size_correction import METHODS

    if method not in METHODS:
        raise ParameterError(
            "size_correction", f"must be one of {', '.join(METHODS)}, got '{method}'"
        )
    if method != "none" and scale_from is None:
        given = "--scale gives no sizes; " if scale is not None else ""
        raise ParameterError(
            ("size_correction", "scale_from"),
            f"{given}a size correction needs --scale-from PTSN_DIR (its scale.json's E_est and "
            "E_pred_at_scale)",
        )


def sweep_size_correction(method: str, scale_from) -> tuple[np.ndarray, dict, float] | None:
    """None for method "none"; else the per-dimension factors (3,) of the sweep `scale_from`,
    the record written to metrics.json and the sweep's ŝ, read once, before any prediction is
    made. E_pred is the sweep's E_pred_at_scale. ArtifactError naming scale.json when it lacks
    E_est or E_pred_at_scale."""
    if method == "none":
        return None
    from dali_cli.labels.size_correction import factors_from_sweep
    from dali_cli.store.artifacts import ArtifactError
    from dali_cli.store.scale_file import read_scale, scale_path

    sweep = read_scale(scale_from)
    e_pred = sweep.e_pred
    try:
        factors = factors_from_sweep(sweep.e_est, e_pred, str(scale_path(scale_from)))
    except ValueError as error:
        raise ArtifactError(str(error)) from None
    record = {
        "method": method,
        "factors_lwh": [round(float(f), 6) for f in factors],
        "E_est": list(sweep.e_est),
        "E_pred_at_scale": list(e_pred),
        "from": str(scale_path(scale_from)),
        "anchor": "bottom face (z moves by half the change of h)",
    }
    return factors, record, sweep.scale


def resized(pred: BoxTable, factors: np.ndarray, class_name: str) -> BoxTable:
    """`pred` with its `class_name` boxes resized by `factors` (3,), bottom face kept."""
    from dali_cli.labels.size_correction import correct_class_sizes

    boxes = correct_class_sizes(pred.boxes, pred["label"], class_name, factors)
    return pred.with_columns(**{name: boxes[:, i] for i, name in enumerate(BOX_FIELDS)})


def saved_metrics_file(pred_path: Path) -> Path:
    """The metrics.json an eval wrote beside the predictions.parquet `pred_path` (or inside the
    directory `pred_path`); it need not exist."""
    return pred_path.parent / METRICS_NAME if pred_path.is_file() else pred_path / METRICS_NAME


def saved_predictions_scale(pred_path: Path) -> float | None:
    """The scale saved predictions were made at, as the eval that saved them recorded it; None
    for predictions from elsewhere (`dali export`, another tool): their scale is unknown."""
    try:
        made_at = read_json_file(saved_metrics_file(pred_path), "metrics file").get("scale")
    except (OSError, ValueError, AttributeError, StageError):
        return None
    if isinstance(made_at, bool) or not isinstance(made_at, int | float):
        return None
    return float(made_at)


def warn_if_made_at_another_scale(
    pred_path: Path, made_at: float | None, scale_from, chosen: float
) -> None:
    """A warning when saved predictions were made at another scale (`made_at`) than `chosen`,
    ŝ of the sweep `scale_from` whose factors correct them: the factors E_est / E_pred hold at
    that ŝ only."""
    if made_at is not None and not np.isclose(made_at, chosen, rtol=1e-9):
        console.warn(
            f"eval: {pred_path} was made at scale {made_at:g} ({saved_metrics_file(pred_path)}), "
            f"the size-correction factors of {scale_from} hold at its scale {chosen:g}"
        )


def predictions_and_truth(
    pred_path, gt_path, model, data, scale, scale_from, device="auto", precision="fp32",
    engine=None, near=None, progress=True, size_correction="none", class_name="Car",
    fusion=None,
):  # fmt: skip
    """(pred, gt, frame ids evaluated or None, source record, gt path, runtime or None) from
    either the model route (`model` on `data`) or the table route (`pred_path` vs `gt_path`),
    the predictions size-corrected when `size_correction` says so (record: source's
    "size_correction"; `run_eval` has checked the method)."""
    # before the detector runs
    correction = sweep_size_correction(size_correction, scale_from)
    frame_ids = runtime = None
    made_at = None  # the table route's scale, from the saving eval's metrics.json
    if model is not None or data is not None:
        if model is None or data is None:
            raise ParameterError(("model", "data"), "the model and its frame set go together")
        if pred_path is not None:
            raise ParameterError(("pred_path", "model"), "give predictions or a model, not both")
        from dali_cli.runtime.device import inference_device, inference_runtime

        torch_device = inference_device(device, precision)  # a missing GPU: error, no output
        chosen_scale = resolve_scale(scale, scale_from)
        frame_ids = FrameSet(data).frame_ids
        gt_path = Path(data) if gt_path is None else gt_path
        pred = predict(
            model, data, chosen_scale, torch_device, precision, engine, near, progress, fusion
        )
        source = {"model": str(model), "data": str(data), "scale": chosen_scale}
        if fusion is not None:
            source["test_time_fusion"] = fusion.record()
        runtime = {**inference_runtime(torch_device), "precision": precision}
    else:
        if scale is not None or (scale_from is not None and size_correction == "none"):
            raise ParameterError(
                ("scale", "scale_from"),
                "a scale only applies with a model (--scale-from without one: only with "
                "--size-correction per-dim, for its factors)",
            )
        if pred_path is None or gt_path is None:
            raise ParameterError(("pred_path", "gt_path"), "give predictions and ground truth")
        pred, _ = read_box_source(pred_path, "pred")
        source = {"pred": str(pred_path)}
        made_at = saved_predictions_scale(Path(pred_path))
        if made_at is not None:
            source["scale"] = made_at
    if correction is not None:
        factors, source["size_correction"], sweep_scale = correction
        if pred_path is not None:
            warn_if_made_at_another_scale(Path(pred_path), made_at, scale_from, sweep_scale)
        pred = resized(pred, factors, class_name)
    gt, label_frames = read_box_source(gt_path, "gt")
    source["gt"] = str(gt_path)
    frames = frame_ids if frame_ids is not None else label_frames
    return pred, gt, frames, source, gt_path, runtime


def run_eval(
    *,
    pred_path: str | Path | None = None,
    gt_path: str | Path | None = None,
    model: str | Path | None = None,
    data: str | Path | None = None,
    scale: float | None = None,
    scale_from: str | Path | None = None,
    ious: tuple[float, ...] = (0.7,),
    size_score_min: float = SCORE_MIN,
    recall_positions: int = 40,
    protocol: str = "auto",
    front_only: bool = False,
    class_name: str = "Car",
    min_gt_points: int = 0,
    out: str | Path | None = None,
    save_predictions: bool = True,
    device: str = "auto",
    precision: str = "fp32",
    executor: str = "local",
    workers: int | None = 1,
    ray_address: str | None = None,
    force: bool = False,
    dry_run: bool = False,
    progress: bool = True,
    size_correction: str = "none",
    calib: str | Path | None = None,
    tta: tuple[bool, tuple[float, ...], float] | None = None,
) -> EvalResult:
    """Evaluate (see the module docstring). `out`: None (print only), a metrics file (.json) or
    an artifact directory; `force` applies to the directory, `dry_run` to both (a metrics file
    is always recomputed, so a dry run only says so and writes nothing); `progress`: the
    detector's progress bar (with --model); `tta`: test-time fusion's (flip, scale factors,
    IoU) (dali_cli.detector.fusion; with --model only)."""
    check_ious(tuple(ious))
    # before any work or output
    check_size_correction(size_correction, scale, scale_from)
    fusion = test_time_fusion(tta, model)
    options = dict(
        ious=tuple(ious), size_score_min=size_score_min, recall_positions=int(recall_positions),
        protocol=protocol, front_only=front_only, class_name=class_name,
        min_gt_points=min_gt_points,
    )  # fmt: skip
    from dali_cli.executors import make_executor

    routes = dict(
        pred_path=pred_path, gt_path=gt_path, model=model, data=data, scale=scale,
        scale_from=scale_from, device=device, precision=precision,
        engine=make_executor(executor, workers, ray_address),
        near=Path(out).parent if out is not None else None, progress=progress,
        size_correction=size_correction, class_name=class_name, calib=calib, fusion=fusion,
    )  # fmt: skip
    inputs = {"model": model, "data": data, "pred": pred_path, "gt": gt_path, "scale": scale_from}
    if calib is not None:  # absent without: older artifacts stay up to date
        inputs["calib"] = calib
    if out is not None and Path(out).suffix != ".json":
        return eval_artifact(Path(out), inputs, routes, options, save_predictions, force, dry_run)
    out = Path(out) if out is not None else None
    if out is not None:  # before any work: an output dali must not write fails at once
        from dali_cli.store.output_paths import check_metrics_output

        keep = keeps_predictions(save_predictions, model, size_correction)
        check_metrics_output(out, inputs, beside=(PREDICTIONS_NAME,) if keep else ())
    if dry_run:  # a metrics file (or the terminal) is not a stage artifact: it is always rerun
        where = out if out is not None else "the terminal"
        console.echo(f"eval: would run -> {where} (a metrics file is always recomputed)")
        return EvalResult({}, [], "dry-run")
    metrics, pred = compute_metrics(routes, options)
    written = []
    if out is not None:
        keep = keeps_predictions(save_predictions, model, size_correction)
        written = write_outputs(out, metrics, pred if keep else None)
    return EvalResult(metrics, written)


def test_time_fusion(tta, model):
    """The TestTimeFusion of `tta` (None when it asks for one pass); a ParameterError when it
    asks for several passes without a model to run them."""
    if tta is None or (not tta[0] and tuple(tta[1]) == (1.0,)):
        return None
    if model is None:
        raise ParameterError(
            ("tta_flip", "tta_scales"), "test-time fusion runs the detector: give --model"
        )
    from dali_cli.detector.fusion import fusion_of

    return fusion_of(tta)


def keeps_predictions(save_predictions: bool, model, size_correction: str) -> bool:
    """Whether predictions.parquet is written: the detector's output (with a model) or the
    corrected boxes (with a size correction), never a copy of a given table."""
    return save_predictions and (model is not None or size_correction != "none")


def refuse_unscorable(pred: BoxTable, gt: BoxTable, pred_where: str, gt_where: str) -> None:
    """StageError for saved predictions an evaluation cannot mean anything of: none of their
    frames among the ground truth's, every score -1 (a label table's, not a detector's), or
    every box of size 0."""
    if len(pred) == 0:
        return
    truth_frames = set(gt.frame_id.astype(str).tolist())
    if truth_frames and not truth_frames.intersection(pred.frame_id.astype(str).tolist()):
        raise StageError(
            f"{pred_where}: no frame in common with the ground truth {gt_where} (its first "
            f"frame is '{pred.frame_id[0]}'): predictions of another frame set?"
        )
    scores = np.asarray(pred["score"], np.float64)
    if np.all(scores == -1):
        raise StageError(
            f"{pred_where}: every score is -1, the mark of a label table, not of predictions; "
            "AP ranks predictions by their scores"
        )
    if np.all(pred.boxes[:, 3:6].prod(axis=1) == 0):
        raise StageError(f"{pred_where}: every box has a size of 0: no prediction to score")


def with_image_boxes_of(pred: BoxTable, calib: str | Path) -> BoxTable:
    """`pred` with the 2D image box and alpha of every box through `calib` (`--calib`: a calib
    file for every frame, a raw drive's date folder, or a folder of <frame>.txt)."""
    from dali_cli.evaluation.image import with_image_boxes
    from dali_cli.importers.calibration import frame_calib, load_calib

    loaded = load_calib(Path(calib))
    return with_image_boxes(pred, lambda frame_id: frame_calib(loaded, frame_id))


def compute_metrics(routes: dict, options: dict) -> tuple[dict, BoxTable]:
    """(the metrics document, the predictions evaluated) of one evaluation."""
    from dali_cli.evaluation.errors import breakdown
    from dali_cli.evaluation.evaluate import EvaluationError, evaluate, scored_boxes

    calib = routes.get("calib")
    pred, gt, frame_ids, source, gt_path, runtime = predictions_and_truth(
        **{name: value for name, value in routes.items() if name != "calib"}
    )
    if calib is not None:  # KITTI's image side: each prediction's 2D box and alpha
        pred = with_image_boxes_of(pred, calib)
    for table, where in ((pred, routes["pred_path"] or "the predictions"), (gt, gt_path)):
        positive = (table.boxes[:, 3:6] > 0).all(axis=1)
        plausibility.refuse_implausible(table.boxes, positive, str(where), table.frame_id)
    if routes["pred_path"] is not None:
        refuse_unscorable(pred, gt, str(routes["pred_path"]), str(gt_path))
    correction = source.pop("size_correction", None)
    class_name = options["class_name"]
    metrics: dict = {}
    boxes = dict(
        protocol=options["protocol"], class_name=class_name,
        min_gt_points=options["min_gt_points"], frame_ids=frame_ids,
        front_only=options["front_only"],
    )  # fmt: skip
    try:
        scored = scored_boxes(pred, gt, **boxes)  # every pair's overlaps, for every threshold
        results = [
            evaluate(
                pred,
                gt,
                iou=iou,
                recall_positions=options["recall_positions"],
                scored=scored,
                **boxes,
            )  # fmt: skip
            for iou in options["ious"]
        ]
    except EvaluationError as error:
        raise StageError(
            f"cannot evaluate {source.get('pred', routes['model'])} against {gt_path}: {error}"
        ) from None
    for index, (iou, result) in enumerate(zip(options["ious"], results, strict=True)):
        block = result[class_name]
        block["source"] = source
        metrics[class_name if index == 0 else f"{class_name}@{iou:g}"] = block
    metrics[ERRORS_KEY] = breakdown(
        pred, gt, ious=options["ious"], recall_positions=options["recall_positions"],
        scored=scored, **boxes,
    )  # fmt: skip
    metrics["sizes"] = {
        "pred": mean_box_size(pred, class_name, score_min=options["size_score_min"]),
        "gt": mean_box_size(gt, class_name),
    }
    if "scale" in source:
        metrics["scale"] = source["scale"]
    if correction is not None:
        metrics["size_correction"] = correction
    if runtime is not None:
        metrics["runtime"] = runtime
    if routes["model"] is not None:
        from dali_cli.store.artifacts import ArtifactError
        from dali_cli.store.model_card import has_direction

        try:
            direction = has_direction(routes["model"])
        except ArtifactError:  # a stand-in detector without a model.json (tests)
            direction = None
        if direction is False:
            console.echo(
                f"eval: {routes['model']} has no direction head (a model from before it): its "
                "yaws are heading axes within ±90° of the sensor's x, so APH, AOS and the "
                "backwards count read which way the axis happens to point"
            )
    return metrics, pred


def marked(table):
    """The Arrow table with the mark that says dali eval wrote it (output_paths.PREDICTIONS_MARK):
    a later `dali eval --out` into that directory replaces only such a file."""
    from dali_cli.store.output_paths import PREDICTIONS_MARK

    return table.replace_schema_metadata(
        {**(table.schema.metadata or {}), PREDICTIONS_MARK[0]: PREDICTIONS_MARK[1]}
    )


def write_outputs(metrics_path: Path, metrics: dict, pred: BoxTable | None) -> list[Path]:
    """metrics.json at `metrics_path` and (given `pred`) predictions.parquet beside it."""
    written = []
    if pred is not None:
        import pyarrow.parquet as pq

        path = metrics_path.parent / PREDICTIONS_NAME
        write_atomically(
            path,
            lambda partial: pq.write_table(marked(pred.to_arrow()), partial, compression="zstd"),
        )
        written.append(path)
    write_text_atomically(metrics_path, json.dumps(metrics, indent=2) + "\n")
    return [*written, metrics_path]


def eval_artifact(out, inputs, routes, options, save_predictions, force, dry_run) -> EvalResult:
    """The evaluation as the artifact directory `out` under the stage contract."""
    from dali_cli.store.manifest import BuildResult, run_stage

    computed: dict = {}

    def build(directory: Path) -> BuildResult:
        metrics, pred = compute_metrics(routes, options)
        keep = keeps_predictions(save_predictions, routes["model"], routes["size_correction"])
        write_outputs(directory / METRICS_NAME, metrics, pred if keep else None)
        computed["metrics"] = metrics
        counts = {"predictions": len(pred), "frames": metrics[options["class_name"]]["frames"]}
        return BuildResult(counts=counts)

    params = {
        **{k: v for k, v in options.items()},
        "scale": routes["scale"],
        "save_predictions": save_predictions,
        "precision": routes["precision"],
    }
    if routes["size_correction"] != "none":  # absent when off: older artifacts stay up to date
        params["size_correction"] = routes["size_correction"]
    if routes["fusion"] is not None:  # likewise
        params["test_time_fusion"] = routes["fusion"].record()
    outcome = run_stage(
        "eval", out, inputs, params, build, force=force, dry_run=dry_run,
        derived=(KITTI_METRICS_NAME,),
    )  # fmt: skip
    if outcome.status == "dry-run":
        return EvalResult({}, [], outcome.status)
    metrics = computed.get("metrics") or read_json_file(out / METRICS_NAME, "metrics file")
    names = (
        [PREDICTIONS_NAME, METRICS_NAME] if (out / PREDICTIONS_NAME).is_file() else [METRICS_NAME]
    )
    return EvalResult(metrics, [out / name for name in names], outcome.status)
