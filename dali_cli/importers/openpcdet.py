"""OpenPCDet's custom dataset format, read and written.

Layout: `ROOT/points/ID.npy` ((n, >=4) float32 x, y, z, intensity, LiDAR frame),
`ROOT/labels/ID.txt` (one box a line: `x y z dx dy dz heading class`, geometric centre, dx along
the heading — the same box convention as dali), optional `ROOT/ImageSets/SPLIT.txt` id lists.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dali_cli.geometry import count_points_in_boxes, wrap_angle
from dali_cli.importers.common import (
    ImportFormatError,
    check_finite_points,
    check_id,
    check_scan_contract,
    read_id_list,
    read_text_lines,
    write_imported,
)
from dali_cli.labels import plausibility
from dali_cli.store.artifacts import BoxTable
from dali_cli.store.frame_ids import child_path
from dali_cli.store.manifest import BuildResult
from dali_cli.store.regular_files import check_regular

DEFAULT_CAR_CLASSES = ("Car", "Vehicle")


def frame_ids(root: str | Path, split: str | None = None) -> list[str]:
    """Ids from ROOT/ImageSets/SPLIT.txt, else every ROOT/points/*.npy stem (sorted)."""
    root = Path(root)
    points_dir = root / "points"
    if not points_dir.is_dir():
        raise ImportFormatError(f"{points_dir}: points directory not found")
    if split is not None:
        ids_path = root / "ImageSets" / f"{split}.txt"
        if not ids_path.is_file():
            raise ImportFormatError(f"{ids_path}: split file not found")
        ids = read_id_list(ids_path)
        missing = [i for i in ids if not (points_dir / f"{i}.npy").is_file()]
        if missing:
            raise ImportFormatError(
                f"{ids_path}: frame '{missing[0]}' has no {points_dir / (missing[0] + '.npy')}"
            )
        return ids
    ids = sorted(check_id(path.stem, f"{path}: file name") for path in points_dir.glob("*.npy"))
    if not ids:
        raise ImportFormatError(f"{points_dir}: no .npy point files")
    return ids


def read_points(path: str | Path, intensity_max: float = 1.0) -> np.ndarray:
    """An OpenPCDet `.npy` cloud -> `(n, 4)` float32, intensity divided by `intensity_max`."""
    path = check_regular(path, "point file")
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as error:
        raise ImportFormatError(f"{path}: cannot read .npy ({error})") from None
    real = array.dtype.kind in "iuf"  # integers or floats: no complex, booleans, strings
    if array.ndim != 2 or array.shape[1] < 4 or not real:
        raise ImportFormatError(
            f"{path}: expected a numeric (n, >=4) array of real numbers, got {array.dtype} {array.shape}"
        )
    points = array[:, :4].astype(np.float32)
    check_finite_points(points, path)
    return check_scan_contract(points, path, intensity_max)


def read_labels(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """One label file -> boxes `(N, 7)` float64 (yaw wrapped to [-pi, pi)) and classes `(N,)`.

    Errors name the file, the line and the field."""
    path = Path(path)
    lines = read_text_lines(path, "label file")
    names = ("x", "y", "z", "dx", "dy", "dz", "heading")
    values, classes = [], []
    for number, line in enumerate(lines, start=1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) != 8:
            raise ImportFormatError(
                f"{path}, line {number}: {len(fields)} fields, expected 8 (x y z dx dy dz heading class)"
            )
        row = []
        for name, text in zip(names, fields[:7], strict=True):
            try:
                value = float(text)
            except ValueError:
                raise ImportFormatError(
                    f"{path}, line {number}: field '{name}' is not a number: {text!r}"
                ) from None
            if not np.isfinite(value):
                raise ImportFormatError(f"{path}, line {number}: field '{name}' is {text}")
            row.append(value)
        if min(row[3:6]) < 0:
            raise ImportFormatError(f"{path}, line {number}: negative size (dx dy dz)")
        values.append(row)
        classes.append(fields[7])
    boxes = np.asarray(values, np.float64).reshape(-1, 7)
    boxes[:, 6] = wrap_angle(boxes[:, 6])
    return boxes, np.asarray(classes, dtype=object)


def build_import(
    out: str | Path,
    root: str | Path,
    frame_ids: list[str],
    car_classes: tuple[str, ...] = DEFAULT_CAR_CLASSES,
    intensity_max: float = 1.0,
    sensor: str = "kitti",
    progress: bool = True,
) -> BuildResult:
    """Stage body of `dali import openpcdet`: FrameSet + boxes into `out`; returns counts
    (`progress`: a progress bar on stderr)."""

    root = Path(root)

    def frames():
        for frame_id in frame_ids:
            points = read_points(root / "points" / f"{frame_id}.npy", intensity_max)
            label_path = root / "labels" / f"{frame_id}.txt"
            table = None
            if label_path.is_file():
                boxes, classes = read_labels(label_path)
                real = classes.astype(str) != "DontCare"  # regions, not objects (size 0)
                plausibility.refuse_implausible(
                    boxes, real, str(label_path), [frame_id] * len(boxes)
                )
                labels = np.where(
                    np.isin(classes.astype(str), list(car_classes)), "Car", classes
                ).astype(object)
                counts = (
                    count_points_in_boxes(points, boxes) if len(boxes) else np.zeros(0, np.int32)
                )
                table = BoxTable.from_arrays(
                    np.full(len(boxes), frame_id, dtype=object),
                    boxes,
                    label=labels,
                    num_points=counts,
                )
            yield frame_id, points, table

    attrs = {"source_format": "openpcdet"}
    return write_imported(
        out,
        frames(),
        sensor,
        attrs,
        total=len(frame_ids),
        progress=progress,
        notes=[f"intensity divided by {intensity_max}"],
    )


def write_dataset(
    root: str | Path,
    frames,
    boxes=None,
    split: str | None = None,
    score_min: float | None = None,
) -> dict:
    """Write `(frame_id, points (n, 4))` pairs and an optional BoxTable in the custom format.

    Every frame gets a points file; frames with boxes (or all frames, when `boxes` is given) get
    a label file. With `split`, ImageSets/SPLIT.txt lists the frames. Returns counts.
    """
    root = Path(root)
    if split is not None:
        split_path = child_path(root / "ImageSets", split, ".txt")  # refuses "../x" before writing
    (root / "points").mkdir(parents=True, exist_ok=True)
    rows = {}
    if boxes is not None:
        if score_min is not None:
            boxes = boxes.select(boxes["score"] >= score_min)
        (root / "labels").mkdir(exist_ok=True)
        rows = boxes.rows_by_frame()
        all_boxes, all_labels = boxes.boxes, boxes["label"]
    ids, written = [], 0
    for frame_id, points in frames:
        # child_path: a second guard, after the id checks where the data entered
        np.save(child_path(root / "points", frame_id, ".npy"), np.asarray(points, np.float32))
        ids.append(frame_id)
        if boxes is not None:
            index = rows.get(frame_id, np.zeros(0, np.int64))
            values, labels = all_boxes[index], all_labels[index]
            lines = [
                " ".join(f"{v:.6f}" for v in values[i]) + f" {labels[i]}" for i in range(len(index))
            ]
            label_path = child_path(root / "labels", frame_id, ".txt")
            label_path.write_text("".join(line + "\n" for line in lines))
            written += len(index)
    if split is not None:
        (root / "ImageSets").mkdir(exist_ok=True)
        split_path.write_text("".join(f"{i}\n" for i in ids))
    return {"frames": len(ids), "boxes": written}
