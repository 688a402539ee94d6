"""KITTI label_2 text files: read them into box tables and write box tables as label files.

A label line is `type truncated occluded alpha left top right bottom h w l x y z ry [score]` in
the camera frame (x right, y down, z forward; location = bottom centre). Without calibration the
boxes are turned into a pseudo-LiDAR frame, x = z_cam, y = -x_cam, z = -y_cam + h/2,
yaw = -ry - pi/2: a rigid motion (camera axes permuted), so every BEV and 3D IoU is preserved and
the evaluation of label files equals that of the box tables they came from. The importer applies
the calibration for the true LiDAR frame.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from dali_cli.geometry import wrap_angle
from dali_cli.store.artifacts import ArtifactError, BoxTable
from dali_cli.store.frame_ids import check_name, child_path

LABEL_SUFFIX = ".txt"
BBOX_COLUMNS = ("bbox_left", "bbox_top", "bbox_right", "bbox_bottom")
DEFAULT_BBOX = (0.0, 0.0, 50.0, 50.0)  # ST3D's stand-in 2D box: passes every difficulty filter
_FIELDS = 15


def camera_to_pseudo_lidar(hwl: np.ndarray, location: np.ndarray, ry: np.ndarray) -> np.ndarray:
    """KITTI camera boxes (dimensions `(N, 3)` h, w, l; bottom-centre `(N, 3)`; ry `(N,)`) as
    pseudo-LiDAR boxes `(N, 7)` float64."""
    hwl, location = (
        np.asarray(hwl, np.float64).reshape(-1, 3),
        np.asarray(location, np.float64).reshape(-1, 3),
    )
    ry = np.asarray(ry, np.float64).reshape(-1)
    return np.stack(
        [
            location[:, 2],
            -location[:, 0],
            -location[:, 1] + hwl[:, 0] / 2,
            hwl[:, 2],
            hwl[:, 1],
            hwl[:, 0],
            wrap_angle(-ry - np.pi / 2),
        ],
        axis=1,
    ).reshape(-1, 7)


def pseudo_lidar_to_camera(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of camera_to_pseudo_lidar: (hwl `(N, 3)`, bottom-centre `(N, 3)`, ry `(N,)`)."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    hwl = boxes[:, [5, 4, 3]]
    location = np.stack([-boxes[:, 1], -(boxes[:, 2] - boxes[:, 5] / 2), boxes[:, 0]], axis=1)
    ry = wrap_angle(-boxes[:, 6] - np.pi / 2)
    return hwl, location, np.asarray(ry).reshape(-1)


def _split_lines(path: Path) -> tuple[list[str], list[str], list[int]]:
    """Names, numeric tokens (15 per line, the score defaulting to 1) and line numbers."""
    from dali_cli.store.regular_files import UnreadableFileError, read_text_file

    try:
        text = read_text_file(path, "label file", "label")
    except UnreadableFileError as error:  # a FIFO, a directory, too large, not UTF-8
        raise ArtifactError(str(error)) from None
    except OSError as error:
        raise ArtifactError(f"{path}: cannot read label file ({error.strerror})") from None
    names, tokens, numbers = [], [], []
    for number, line in enumerate(text.splitlines(), start=1):  # a loop over text lines
        fields = line.split()
        if not fields:
            continue
        if len(fields) not in (_FIELDS, _FIELDS + 1):
            raise ArtifactError(
                f"{path}:{number}: expected {_FIELDS} or {_FIELDS + 1} fields, got {len(fields)}"
            )
        names.append(fields[0])
        tokens.extend(fields[1:])
        if len(fields) == _FIELDS:
            tokens.append("1")
        numbers.append(number)
    return names, tokens, numbers


def _parse(files: list[Path], frame_ids: list[str]) -> BoxTable:
    """Label lines of several files as one box table (see read_label_file)."""
    names, tokens, origin, numbers = [], [], [], []
    for index, path in enumerate(files):
        file_names, file_tokens, file_numbers = _split_lines(path)
        names += file_names
        tokens += file_tokens
        numbers += file_numbers
        origin += [index] * len(file_names)
    try:
        data = np.asarray(tokens, dtype=np.float64).reshape(-1, _FIELDS)
    except ValueError:  # find the offending line for the message
        for row in range(len(names)):
            for column, value in enumerate(tokens[row * _FIELDS : (row + 1) * _FIELDS]):
                if not _is_float(value):
                    raise ArtifactError(
                        f"{files[origin[row]]}:{numbers[row]}: field {column + 2} ('{value}') "
                        "is not a number"
                    ) from None
        raise
    names_array = np.asarray(names, dtype=object)
    dont_care = np.asarray([name.lower() == "dontcare" for name in names], dtype=bool)
    hwl = data[:, 7:10].copy()
    finite = np.isfinite(data).all(axis=1)
    occluded = np.where(finite, data[:, 1], 0.0)
    not_int32 = (occluded != np.round(occluded)) | (np.abs(occluded) > np.iinfo(np.int32).max)
    bad = ~finite | ((hwl < 0).any(axis=1) & ~dont_care) | not_int32
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        problem = (
            "non-finite value"
            if not finite[row]
            else f"field 3 (occluded) {data[row, 1]:g} is not an integer"
            if not_int32[row]
            else "negative box dimension"
        )
        raise ArtifactError(f"{files[origin[row]]}:{numbers[row]}: {problem}")
    hwl[dont_care] = np.maximum(hwl[dont_care], 0.0)
    boxes = camera_to_pseudo_lidar(hwl, data[:, 10:13], data[:, 13])
    return BoxTable.from_arrays(
        np.asarray(frame_ids, dtype=object)[np.asarray(origin, dtype=np.int64)],
        boxes,
        score=data[:, 14].astype(np.float32),
        label=names_array,
        truncated=data[:, 0].astype(np.float32),
        occluded=data[:, 1].astype(np.int32),
        alpha=data[:, 2].astype(np.float64),
        **{name: data[:, 3 + k].astype(np.float32) for k, name in enumerate(BBOX_COLUMNS)},
    )


def read_label_file(path: str | Path, frame_id: str | None = None) -> BoxTable:
    """One label file as a box table (frame id = the file's stem unless given).

    Columns: the box, label (KITTI type), score (16th field, else 1), and the KITTI columns
    truncated, occluded, alpha, bbox_left/top/right/bottom. DontCare's placeholder size -1
    becomes 0. Raises ArtifactError naming the file, line and field on malformed input.
    """
    path = Path(path)
    return _parse([path], [path.stem if frame_id is None else str(frame_id)])


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def label_files(directory: str | Path) -> list[Path]:
    """The `<frame>.txt` files of a label directory, sorted by name; each stem must be a valid
    frame id (dali_cli.store.frame_ids), FrameIdError naming the file otherwise."""
    directory = Path(directory)
    if not directory.is_dir():
        raise ArtifactError(f"{directory}: label directory not found")
    files = sorted(p for p in directory.iterdir() if p.suffix == LABEL_SUFFIX and p.is_file())
    for path in files:
        check_name(path.stem, f"{path}: file name")
    return files


def list_label_frames(directory: str | Path) -> list[str]:
    """Frame ids (file stems) of a label directory, empty files included."""
    return [path.stem for path in label_files(directory)]


def read_label_dir(directory: str | Path) -> BoxTable:
    """Every `<frame>.txt` of a label_2-style directory as one box table (see read_label_file)."""
    files = label_files(directory)
    if not files:
        raise ArtifactError(f"{directory}: no {LABEL_SUFFIX} label files")
    return _parse(files, [path.stem for path in files])


def format_label_lines(table: BoxTable, with_score: bool = True, decimals: int = 6) -> list[str]:
    """Label lines for the rows of `table` (normally one frame), in row order.

    Missing KITTI columns get defaults: truncated 0, occluded 0, the 2D box [0, 0, 50, 50] and
    alpha = ry - atan2(x_cam, z_cam). Scores are written with 9 significant digits, enough to
    round-trip float32 exactly.
    """
    count = len(table)
    hwl, location, ry = pseudo_lidar_to_camera(table.boxes)
    columns = table.columns
    truncated = np.asarray(columns.get("truncated", np.zeros(count)), dtype=np.float64)
    occluded = np.asarray(columns.get("occluded", np.zeros(count)), dtype=np.int64)
    default_alpha = wrap_angle(ry - np.arctan2(location[:, 0], location[:, 2]))
    alpha = np.asarray(columns.get("alpha", default_alpha), dtype=np.float64)
    bbox = np.stack(
        [
            np.asarray(columns.get(name, np.full(count, value)), np.float64)
            for name, value in zip(BBOX_COLUMNS, DEFAULT_BBOX, strict=True)
        ],
        axis=1,
    ).reshape(-1, 4)
    labels = np.asarray(columns["label"], dtype=str)
    scores = np.asarray(columns["score"], dtype=np.float32)
    f = f"{{:.{decimals}f}}"
    lines = []
    for k in range(count):  # one formatted line per box: a loop over text, not over points
        if labels[k].lower() == "dontcare":
            geometry = "-1 -1 -1 -1000 -1000 -1000 -10"
        else:
            geometry = " ".join(f.format(v) for v in (*hwl[k], *location[k], ry[k]))
        fields = [
            labels[k],
            f"{truncated[k]:.2f}",
            str(int(occluded[k])),
            f.format(alpha[k]),
            *(f"{v:.2f}" for v in bbox[k]),
            geometry,
        ]
        if with_score:
            fields.append(f"{float(scores[k]):.9g}")
        lines.append(" ".join(fields))
    return lines


def write_label_dir(
    directory: str | Path,
    table: BoxTable,
    frame_ids: Iterable[str] | None = None,
    with_score: bool = True,
    decimals: int = 6,
) -> int:
    """Write one `<frame>.txt` per frame (empty files for frames without boxes); returns the
    number of files. `frame_ids` defaults to the frames present in the table."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    rows = table.rows_by_frame()
    frames = sorted(rows) if frame_ids is None else [str(f) for f in frame_ids]
    for frame in frames:
        path = child_path(directory, frame, LABEL_SUFFIX)  # FrameIdError unless inside directory
        selected = rows.get(frame, np.zeros(0, np.int64))
        lines = format_label_lines(table.select(selected), with_score, decimals)
        path.write_text("".join(line + "\n" for line in lines))
    return len(frames)


def read_box_source(path: str | Path, role: str) -> tuple[BoxTable, list[str] | None]:
    """A box table from a parquet dir/file or a label directory, plus the label files' frames
    (None for a table). ParameterError on `{role}_path` for anything else."""
    from dali_cli.runtime.errors import ParameterError
    from dali_cli.store.artifacts import BOXES_NAME, read_boxes

    path = Path(path)
    if path.is_file() and path.suffix == ".parquet":
        return read_boxes(path), None
    if path.is_dir() and (path / BOXES_NAME).is_file():
        return read_boxes(path), None
    if path.is_dir() and (path / "label_2").is_dir():
        path = path / "label_2"
    if path.is_dir() and any(path.glob("*.txt")):
        return read_label_dir(path), list_label_frames(path)
    raise ParameterError(
        f"{role}_path",
        f"{path}: neither a box table ({BOXES_NAME}) nor a directory of label .txt files",
    )
