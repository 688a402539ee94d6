"""Stages export_kitti and export_openpcdet: dali box tables (and frames) -> KITTI label_2 files or
OpenPCDet's custom format (dali_cli.export, dali_cli.importers.openpcdet)."""

from __future__ import annotations

from pathlib import Path

from dali_cli.store.manifest import StageOutcome, run_stage


def export_frame_ids(table, frames_dir: Path | None) -> list[str]:
    """Frames of the FrameSet (when given), then any other frame of the box table, in order."""
    from dali_cli.store.artifacts import FrameSet

    ids = list(FrameSet(frames_dir).frame_ids) if frames_dir is not None else []
    known = set(ids)
    for frame_id in dict.fromkeys(table.frame_id.astype(str).tolist()):
        if frame_id not in known:
            ids.append(frame_id)
            known.add(frame_id)
    return ids


def export_kitti(
    boxes_dir: str | Path,
    calib_root: str | Path,
    out: str | Path,
    *,
    split: str = "training",
    frames_dir: str | Path | None = None,
    image_size: tuple[int, int] | None = None,
    score_min: float | None = None,
    keep_outside: bool = False,
    project_bbox: bool = False,
    with_score: bool = True,
    force: bool = False,
    dry_run: bool = False,
    progress: bool = True,
) -> StageOutcome:
    """KITTI label_2 files `out`/data/<frame>.txt of the box table `boxes_dir` through the
    calib files under `calib_root` (every frame of `frames_dir`, or of the box table's dir);
    `progress`: a progress bar on stderr."""
    from dali_cli.export import build_export_kitti
    from dali_cli.importers.kitti import find_calib_dir
    from dali_cli.store.artifacts import FRAMES_NAME, read_boxes

    table = read_boxes(boxes_dir)
    if score_min is not None:
        table = table.select(table["score"] >= score_min)
    if frames_dir is None and (Path(boxes_dir) / FRAMES_NAME).is_dir():
        frames_dir = Path(boxes_dir)
    frame_ids = export_frame_ids(table, Path(frames_dir) if frames_dir else None)
    calib_dir = find_calib_dir(calib_root, split)
    image_dir = calib_dir.parent / "image_2"
    params = {
        "split": split,
        "image_size": image_size,
        "score_min": score_min,
        "keep_outside": keep_outside,
        "project_bbox": project_bbox,
        "score": with_score,
        "frames": len(frame_ids),
    }
    return run_stage(
        "export-kitti",
        out,
        {"boxes": boxes_dir, "calib": calib_dir, "frames": frames_dir},
        params,
        lambda tmp: build_export_kitti(
            tmp,
            table,
            frame_ids,
            calib_dir,
            image_dir if image_dir.is_dir() else None,
            image_size,
            keep_outside,
            reuse_columns=not project_bbox,
            with_score=with_score,
            progress=progress,
        ),  # fmt: skip
        force=force,
        dry_run=dry_run,
    )


def export_openpcdet(
    data_dir: str | Path,
    out: str | Path,
    *,
    boxes_dir: str | Path | None = None,
    split: str | None = None,
    score_min: float | None = None,
    force: bool = False,
    dry_run: bool = False,
) -> StageOutcome:
    """The FrameSet `data_dir` as `out`/points/<frame>.npy and, with boxes (`boxes_dir`, else
    the frame set's own), `out`/labels/<frame>.txt."""
    from dali_cli.importers.openpcdet import write_dataset
    from dali_cli.store.artifacts import BOXES_NAME, FrameSet, read_boxes

    frames = FrameSet(data_dir)
    if boxes_dir is None and (Path(data_dir) / BOXES_NAME).is_file():
        boxes_dir = data_dir
    table = read_boxes(boxes_dir) if boxes_dir is not None else None
    if table is not None:
        from dali_cli.labels.plausibility import refuse_implausible_table
        from dali_cli.store.artifacts import check_frames_known

        check_frames_known(table, frames.frame_ids, str(boxes_dir))
        refuse_implausible_table(table, str(boxes_dir))
    return run_stage(
        "export-openpcdet",
        out,
        {"frames": data_dir, "boxes": boxes_dir},
        {"split": split, "score_min": score_min},
        lambda tmp: write_dataset(tmp, frames.iter_frames(), table, split, score_min),
        force=force,
        dry_run=dry_run,
    )


def export_model(
    model_dir: str | Path,
    out: str | Path,
    *,
    scale: float | None = None,
    scale_from: str | Path | None = None,
    force: bool = False,
    dry_run: bool = False,
) -> StageOutcome:
    """The detector of `model_dir` as ONNX graphs in `out` (dali_cli.detector.onnx_export) at PTSN
    scale `scale`, `scale_from`'s scale.json, or the model's own scale.json (else 1)."""
    from dali_cli.store.scale_file import model_scale

    scale = model_scale(model_dir, scale, scale_from)

    def build(tmp: Path) -> dict:
        from dali_cli.detector.infer import Detector
        from dali_cli.detector.onnx_export import export_onnx

        spec = export_onnx(Detector.load(model_dir), tmp, scale)
        return {"opset": spec["opset"], "rows": spec["grid"]["rows"], "cols": spec["grid"]["cols"]}

    return run_stage(
        "export-model", out, {"model": model_dir, "scale": scale_from}, {"scale": scale, "format": "onnx"},
        build, force=force, dry_run=dry_run,
    )  # fmt: skip
