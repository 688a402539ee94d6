"""Stage size_norm: a labelled frame set with its cars shifted to a model's size convention
(dali_cli.detector.size_norm): OUT/frames.zarr, OUT/boxes.parquet (the input rows, shifted boxes' z, l, w,
h replaced), OUT/manifest.json."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dali_cli.runtime.errors import ParameterError, StageError
from dali_cli.store.manifest import BuildResult, StageOutcome, run_stage


def size_norm(
    data: str | Path,
    out: str | Path,
    *,
    delta_lwh: tuple[float, float, float] | None = None,
    like_model: str | Path | None = None,
    labels: tuple[str, ...] = ("Car",),
    force: bool = False,
    dry_run: bool = False,
) -> StageOutcome:
    """`data`'s boxes of `labels` shifted by `delta_lwh` (m), or by the SN shift `like_model`
    was trained with; every other row and point as it was."""
    from dali_cli.detector.size_norm import model_delta

    if (delta_lwh is None) == (like_model is None):
        raise ParameterError(("delta_lwh", "like_model"), "give exactly one: a delta or a model")
    delta = np.asarray(model_delta(like_model) if like_model else delta_lwh, np.float64)
    params = {"delta_lwh_m": [round(float(v), 9) for v in delta], "labels": list(labels)}
    inputs = {"data": data} if like_model is None else {"data": data, "model": like_model}
    return run_stage(
        "size_norm", out, inputs, params,
        lambda tmp: build(Path(data), tmp, delta, labels),
        force=force, dry_run=dry_run,
    )  # fmt: skip


def build(data: Path, out: Path, delta: np.ndarray, labels: tuple[str, ...]) -> BuildResult:
    """Write the shifted frame set into `out`; StageError naming the frame and row of a box the
    shift would leave without a positive size (nothing is written then)."""
    from dali_cli.detector.size_norm import shift_frame, too_small
    from dali_cli.store.artifacts import FrameSet, FrameSetWriter, read_boxes, write_boxes

    frames, table = FrameSet(data), read_boxes(data)
    rows_of = table.rows_by_frame()
    shifted_rows = np.flatnonzero(np.isin(table["label"].astype(str), labels))
    small = shifted_rows[too_small(table.boxes[shifted_rows], delta)]
    if len(small):
        row = int(small[0])
        raise StageError(
            f"{data}: frame '{table.frame_id[row]}', box row {row} ({table['label'][row]}, l/w/h "
            f"{table.boxes[row, 3:6].round(3).tolist()} m) would have no positive size after a "
            f"shift of {delta.round(3).tolist()} m"
        )
    boxes = table.boxes.copy()
    selected = np.zeros(len(table), bool)
    selected[shifted_rows] = True
    attrs = {**_carried_attrs(frames.attrs), "size_norm_delta_lwh_m": delta.tolist()}
    with FrameSetWriter(out, frames.sensor, attrs) as writer:
        for frame_id, points in frames.iter_frames():
            rows = rows_of.get(frame_id, np.zeros(0, np.int64))
            rows = rows[selected[rows]]
            new_points, boxes[rows] = shift_frame(points, boxes[rows], delta)
            writer.append(frame_id, new_points)
    names = ("z", "l", "w", "h")
    write_boxes(out, table.with_columns(**{n: boxes[:, 2 + i] for i, n in enumerate(names)}))
    return BuildResult(counts={"frames": len(frames), "boxes_shifted": int(len(shifted_rows))})


def _carried_attrs(attrs: dict) -> dict:
    """The input frame set's attributes a derived set keeps (not its count or writer flags)."""
    from dali_cli.store.artifacts import COMPLETE_CHUNKS_ATTR

    return {k: v for k, v in attrs.items() if k not in ("sensor", "count", COMPLETE_CHUNKS_ATTR)}
