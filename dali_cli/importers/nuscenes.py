"""nuScenes LIDAR_TOP key frames with boxes, without the devkit.

Boxes come either from the v1.0 JSON tables (sample_annotation in the global frame, size w, l, h,
quaternions w, x, y, z; ego_pose and calibrated_sensor give global -> ego -> LiDAR) or from a CSV
already in the LiDAR frame. nuScenes' LiDAR frame has x right, y forward; by default dali turns it
by -90 degrees about z so that x points forward (x' = y, y' = -x, yaw' = yaw - pi/2).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dali_cli.geometry import count_points_in_boxes, wrap_angle
from dali_cli.importers.common import (
    ImportFormatError,
    check_id,
    read_float_records,
    write_imported,
)
from dali_cli.labels import plausibility
from dali_cli.store.artifacts import BoxTable, TableValueError, int32_column
from dali_cli.store.manifest import BuildResult
from dali_cli.store.regular_files import read_json_file

_INT32 = np.iinfo(np.int32)

DEFAULT_CAR_CATEGORIES = ("vehicle.car", "car")
INTENSITY_MAX = 255.0  # nuScenes intensities are 0..255
LIDAR_CHANNEL = "LIDAR_TOP"
CSV_COLUMNS = ("category", "x", "y", "z", "l", "w", "h", "yaw")


def read_pcd_bin(path: str | Path) -> np.ndarray:
    """A LIDAR_TOP `.pcd.bin` (float32 x, y, z, intensity, ring) -> `(n, 4)` float32 with the
    intensity scaled to [0, 1] and the ring index dropped. Sensor frame of nuScenes (x right)."""
    from dali_cli.importers.common import check_scan_contract

    records = read_float_records(path, 5)
    points = records[:, :4].copy()
    points[:, 3] = np.clip(points[:, 3] / INTENSITY_MAX, 0.0, 1.0)
    return check_scan_contract(points, path)


def quaternion_to_matrix(quaternions: np.ndarray) -> np.ndarray:
    """`(N, 4)` quaternions (w, x, y, z), normalized here -> `(N, 3, 3)` rotation matrices."""
    q = np.asarray(quaternions, np.float64).reshape(-1, 4)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    if (norm < 1e-9).any():
        raise ValueError("zero quaternion")
    w, x, y, z = (q / norm).T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1),
        ],
        axis=1,
    )  # (N, 3, 3)


def global_boxes_to_lidar(
    translation: np.ndarray,
    size_wlh: np.ndarray,
    rotation: np.ndarray,
    ego_translation: np.ndarray,
    ego_rotation: np.ndarray,
    sensor_translation: np.ndarray,
    sensor_rotation: np.ndarray,
) -> np.ndarray:
    """Global-frame nuScenes boxes -> `(N, 7)` LiDAR-frame boxes (x, y, z, l, w, h, yaw).

    translation : (N, 3) box centres; size_wlh : (N, 3); rotation : (N, 4) quaternions (w, x, y, z).
    ego_* : the ego pose (3,), (4,) of the LiDAR sweep; sensor_* : the LiDAR's calibrated_sensor
    pose in the ego frame. p_lidar = R_s^T (R_e^T (p - t_e) - t_s); the yaw is the heading of the
    box's x axis after the same rotation.
    """
    ego_r = quaternion_to_matrix(ego_rotation)[0]
    sensor_r = quaternion_to_matrix(sensor_rotation)[0]
    to_lidar = sensor_r.T @ ego_r.T  # (3, 3) global -> LiDAR rotation
    centre = (
        np.asarray(translation, np.float64).reshape(-1, 3) - ego_translation
    ) @ ego_r  # (N, 3)
    centre = (centre - sensor_translation) @ sensor_r  # (N, 3)
    box_r = to_lidar @ quaternion_to_matrix(rotation)  # (N, 3, 3)
    yaw = wrap_angle(np.arctan2(box_r[:, 1, 0], box_r[:, 0, 0]))
    size = np.asarray(size_wlh, np.float64).reshape(-1, 3)
    return np.c_[centre, size[:, 1], size[:, 0], size[:, 2], yaw]


def to_x_forward(points: np.ndarray | None, boxes: np.ndarray | None):
    """Turn nuScenes LiDAR axes (x right, y forward) into dali's (x forward, y left): -90 deg
    about z. points (n, >=3), boxes (N, 7); returns copies (None stays None)."""
    if points is not None:
        points = points.copy()
        points[:, 0], points[:, 1] = points[:, 1].copy(), -points[:, 0]
    if boxes is not None:
        boxes = boxes.copy()
        boxes[:, 0], boxes[:, 1] = boxes[:, 1].copy(), -boxes[:, 0]
        boxes[:, 6] = wrap_angle(boxes[:, 6] - np.pi / 2)
    return points, boxes


def map_labels(categories: np.ndarray, car_categories: tuple[str, ...]) -> np.ndarray:
    """`(N,)` category names -> labels: 'Car' for the car categories, the name otherwise."""
    categories = np.asarray(categories, dtype=object).astype(str)
    return np.where(np.isin(categories, list(car_categories)), "Car", categories).astype(object)


@dataclass(frozen=True)
class Sample:
    """One key frame: its id (the .pcd.bin name without extension), scan path and source key."""

    frame_id: str
    lidar_path: Path
    key: str


# ---------------------------------------------------------------------------------------------
# The v1.0 JSON tables


def _load_table(table_dir: Path, name: str, required: bool = True) -> list[dict] | None:
    path = table_dir / f"{name}.json"
    if not path.is_file():
        if required:
            raise ImportFormatError(f"{path}: nuScenes table missing")
        return None
    from dali_cli.store.regular_files import UnreadableFileError

    try:
        rows = read_json_file(path, "nuScenes table", "dataset_json")
    except UnreadableFileError as error:  # a FIFO, too large, not UTF-8, not JSON, too deep
        raise ImportFormatError(str(error)) from None
    except OSError as error:
        raise ImportFormatError(f"{path}: cannot read nuScenes table ({error})") from None
    if not isinstance(rows, list):
        raise ImportFormatError(f"{path}: expected a JSON list of records")
    _check_records(rows, path, _TABLE_FIELDS.get(name, {}))
    return rows


# The fields dali reads from each table's records and their kinds ("?": may be absent). Checked
# when a table is loaded, so a malformed record is an error naming the file, record and field
# rather than a KeyError or a NaN box later. Annotation geometry is checked per sample in load().
_TABLE_FIELDS = {
    "sensor": {"token": "str", "channel?": "str"},
    "calibrated_sensor": {"token": "str", "sensor_token?": "str", "translation": "vec3",
                          "rotation": "quaternion"},
    "ego_pose": {"token": "str", "translation": "vec3", "rotation": "quaternion"},
    "sample_data": {"sample_token": "str", "ego_pose_token": "str", "filename": "str",
                    "calibrated_sensor_token?": "str", "is_key_frame?": "bool"},
    "sample": {"token": "str", "scene_token?": "str", "timestamp?": "number"},
    "scene": {"token": "str", "name?": "str"},
    "category": {"token": "str", "name": "str"},
    "instance": {"token": "str", "category_token?": "str"},
    "sample_annotation": {"sample_token": "str", "instance_token?": "str"},
}  # fmt: skip


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and np.isfinite(value)


def _kind_problem(value, kind: str) -> str | None:
    """Why `value` is not of `kind` (see _TABLE_FIELDS), or None."""
    if kind == "str":
        return None if isinstance(value, str) else f"expected a string, got {value!r:.40}"
    if kind == "bool":
        return None if isinstance(value, bool) else f"expected true/false, got {value!r:.40}"
    if kind == "number":
        return None if _is_number(value) else f"expected a finite number, got {value!r:.40}"
    size = 3 if kind == "vec3" else 4
    if not (isinstance(value, list) and len(value) == size and all(map(_is_number, value))):
        return f"expected {size} finite numbers, got {value!r:.60}"
    if kind == "quaternion" and np.linalg.norm(value) < 1e-9:
        return "zero quaternion"
    return None


def _check_records(rows: list, path: Path, fields: dict[str, str]) -> None:
    """ImportFormatError naming the file, record (0-based) and field of the first bad record."""
    for index, row in enumerate(rows):  # a loop over records: table rows, not points
        if not isinstance(row, dict):
            raise ImportFormatError(f"{path}: record {index} is not a JSON object")
        for key, kind in fields.items():
            name = key.rstrip("?")
            if name not in row:
                if key.endswith("?"):
                    continue
                raise ImportFormatError(f"{path}: record {index} has no field '{name}'")
            problem = _kind_problem(row[name], kind)
            if problem is not None:
                raise ImportFormatError(f"{path}: record {index}, field '{name}': {problem}")


def _field(rows: list[dict], index: int, name: str, path: Path):
    try:
        return rows[index][name]
    except (KeyError, TypeError):
        raise ImportFormatError(f"{path}: record {index} has no field '{name}'") from None


def _annotation_index(table_dir: Path) -> tuple[dict[str, list[dict]] | None, dict[str, str]]:
    """(sample token -> its sample_annotation records, or None when the table is absent or
    empty (the test split: an unlabelled set); instance token -> category name)."""
    annotations_rows = _load_table(table_dir, "sample_annotation", required=False)
    if not annotations_rows:
        return None, {}
    annotations: dict[str, list[dict]] = {}
    for row in annotations_rows:
        annotations.setdefault(row.get("sample_token"), []).append(row)
    categories = {r["token"]: r["name"] for r in _load_table(table_dir, "category")}
    category_of_instance = {
        r["token"]: categories.get(r.get("category_token"), "unknown")
        for r in _load_table(table_dir, "instance")
    }
    return annotations, category_of_instance


@dataclass
class JsonSource:
    """Key-frame LIDAR_TOP samples of a nuScenes data root and their annotations."""

    root: Path
    table_dir: Path
    _samples: list[Sample]
    _poses: dict[str, tuple]  # sample token -> (ego_t, ego_q, sensor_t, sensor_q)
    _annotations: dict[str, list[dict]] | None  # sample token -> records; None: no annotations
    _category_of_instance: dict[str, str]

    @classmethod
    def of(
        cls, root: str | Path, version: str = "v1.0-mini", scenes: list[str] | None = None
    ) -> JsonSource:
        root = Path(root)
        table_dir = root / version
        if not table_dir.is_dir():
            raise ImportFormatError(
                f"{table_dir}: nuScenes table directory not found (see --version)"
            )
        sensors = _load_table(table_dir, "sensor")
        calibrated = _load_table(table_dir, "calibrated_sensor")
        sample_data = _load_table(table_dir, "sample_data")
        samples = _load_table(table_dir, "sample")
        ego_poses = _load_table(table_dir, "ego_pose")
        scene_rows = _load_table(table_dir, "scene")
        lidar_sensors = {r["token"] for r in sensors if r.get("channel") == LIDAR_CHANNEL}
        if not lidar_sensors:
            raise ImportFormatError(f"{table_dir / 'sensor.json'}: no {LIDAR_CHANNEL} sensor")
        calib_by_token = {
            r["token"]: r for r in calibrated if r.get("sensor_token") in lidar_sensors
        }
        pose_by_token = {r["token"]: r for r in ego_poses}
        scene_of_sample = {r["token"]: r.get("scene_token") for r in samples}
        time_of_sample = {r["token"]: r.get("timestamp", 0) for r in samples}
        scene_name = {r["token"]: r.get("name") for r in scene_rows}
        if scenes is not None:
            unknown = sorted(set(scenes) - set(scene_name.values()))
            if unknown:
                raise ImportFormatError(f"{table_dir / 'scene.json'}: unknown scene '{unknown[0]}'")
        path = table_dir / "sample_data.json"
        chosen: list[tuple] = []
        record_of_frame: dict[str, int] = {}
        poses: dict[str, tuple] = {}
        for index, row in enumerate(sample_data):
            calib = calib_by_token.get(row.get("calibrated_sensor_token"))
            if calib is None or not row.get("is_key_frame", False):
                continue
            sample_token = _field(sample_data, index, "sample_token", path)
            if (
                scenes is not None
                and scene_name.get(scene_of_sample.get(sample_token)) not in scenes
            ):
                continue
            pose = pose_by_token.get(_field(sample_data, index, "ego_pose_token", path))
            if pose is None:
                raise ImportFormatError(f"{path}: record {index} refers to a missing ego_pose")
            filename = Path(_field(sample_data, index, "filename", path))
            frame_id = filename.name.removesuffix(".bin").removesuffix(".pcd")
            check_id(frame_id, f"{path}, record {index} (field 'filename')")
            if frame_id in record_of_frame:
                raise ImportFormatError(
                    f"{path}, record {index}: frame id '{frame_id}' (field 'filename') already "
                    f"used by record {record_of_frame[frame_id]}"
                )
            record_of_frame[frame_id] = index
            poses[sample_token] = (
                np.asarray(pose["translation"], np.float64),
                np.asarray(pose["rotation"], np.float64),
                np.asarray(calib["translation"], np.float64),
                np.asarray(calib["rotation"], np.float64),
            )
            order = (
                scene_name.get(scene_of_sample.get(sample_token), ""),
                time_of_sample.get(sample_token, 0),
            )
            chosen.append((order, Sample(frame_id, root / filename, sample_token)))
        if not chosen:
            raise ImportFormatError(f"{path}: no {LIDAR_CHANNEL} key frames selected")
        chosen.sort(key=lambda item: item[0])
        annotations, category_of_instance = _annotation_index(table_dir)
        return cls(
            root, table_dir, [s for _, s in chosen], poses, annotations, category_of_instance
        )

    def samples(self) -> list[Sample]:
        return list(self._samples)

    def lidar_dir(self) -> Path:
        return self.root / "samples" / LIDAR_CHANNEL

    def load(self, sample: Sample, car_categories: tuple[str, ...], x_forward: bool = True):
        """Points `(n, 4)` and `(boxes (N, 7), labels (N,), num_lidar_pts (N,))` or None."""
        points = read_pcd_bin(sample.lidar_path)
        if self._annotations is None:
            boxes = None
        else:
            rows = self._annotations.get(sample.key, [])
            path = self.table_dir / "sample_annotation.json"
            try:
                translation = np.array([r["translation"] for r in rows], np.float64).reshape(-1, 3)
                size = np.array([r["size"] for r in rows], np.float64).reshape(-1, 3)
                rotation = np.array([r["rotation"] for r in rows], np.float64).reshape(-1, 4)
            except (KeyError, ValueError, TypeError) as error:
                raise ImportFormatError(
                    f"{path}: malformed annotation of sample '{sample.key}' ({error})"
                ) from None
            if not (
                np.isfinite(translation).all()
                and np.isfinite(size).all()
                and np.isfinite(rotation).all()
            ):
                raise ImportFormatError(
                    f"{path}: NaN/inf in an annotation of sample '{sample.key}'"
                )
            if (size < 0).any():
                raise ImportFormatError(
                    f"{path}: negative size in an annotation of sample '{sample.key}'"
                )
            boxes = global_boxes_to_lidar(translation, size, rotation, *self._poses[sample.key])
            categories = np.array(
                [self._category_of_instance.get(r.get("instance_token"), "unknown") for r in rows],
                dtype=object,
            )
            try:
                lidar_pts = int32_column(
                    np.array([r.get("num_lidar_pts", -1) for r in rows], dtype=object).astype(
                        np.float64
                    ),
                    "num_lidar_pts",
                )
            except (TableValueError, ValueError, TypeError) as error:
                raise ImportFormatError(
                    f"{path}: annotation of sample '{sample.key}': field 'num_lidar_pts' ({error})"
                ) from None
        if x_forward:
            points, boxes = to_x_forward(points, boxes)
        if boxes is None:
            return points, None
        return points, (boxes, map_labels(categories, car_categories), lidar_pts)


# ---------------------------------------------------------------------------------------------
# LiDAR-frame CSV


@dataclass
class CsvSource:
    """`.pcd.bin` scans (one file or a directory) with boxes from a LiDAR-frame CSV."""

    root: Path
    csv_path: Path
    _samples: list[Sample]
    _rows: dict[
        str, tuple[np.ndarray, np.ndarray, np.ndarray]
    ]  # frame id -> boxes, categories, pts

    @classmethod
    def of(cls, path: str | Path, csv_path: str | Path) -> CsvSource:
        path, csv_path = Path(path), Path(csv_path)
        files = sorted(path.glob("*.pcd.bin")) if path.is_dir() else [path]
        if not files:
            raise ImportFormatError(f"{path}: no .pcd.bin files")
        samples = [
            Sample(
                check_id(f.name.removesuffix(".bin").removesuffix(".pcd"), f"{f}: file name"),
                f,
                f.name,
            )
            for f in files
        ]
        ids = {s.frame_id for s in samples}
        frame_of_row, boxes, categories, lidar_pts = read_boxes_csv(csv_path)
        if frame_of_row is None:
            if len(samples) != 1:
                raise ImportFormatError(
                    f"{csv_path}: no 'frame_id' column, so PATH must be a single .pcd.bin ({len(samples)} found)"
                )
            frame_of_row = np.full(len(boxes), samples[0].frame_id, dtype=object)
        unknown = sorted(set(frame_of_row.tolist()) - ids)
        if unknown:
            raise ImportFormatError(
                f"{csv_path}: frame_id '{unknown[0]}' has no .pcd.bin under {path}"
            )
        order = np.argsort(frame_of_row.astype(str), kind="stable")  # group rows by frame
        grouped = frame_of_row.astype(str)[order]
        starts = np.searchsorted(grouped, [s.frame_id for s in samples], side="left")
        stops = np.searchsorted(grouped, [s.frame_id for s in samples], side="right")
        rows = {}
        for sample, start, stop in zip(samples, starts, stops, strict=True):
            index = order[start:stop]
            rows[sample.frame_id] = (boxes[index], categories[index], lidar_pts[index])
        return cls(path, csv_path, samples, rows)

    def samples(self) -> list[Sample]:
        return list(self._samples)

    def load(self, sample: Sample, car_categories: tuple[str, ...], x_forward: bool = True):
        points = read_pcd_bin(sample.lidar_path)
        boxes, categories, lidar_pts = self._rows[sample.frame_id]
        if x_forward:
            points, boxes = to_x_forward(points, boxes)
        return points, (boxes, map_labels(categories, car_categories), lidar_pts)


def read_boxes_csv(path: str | Path):
    """Parse a LiDAR-frame box CSV: columns category, x, y, z, l, w, h, yaw, optional
    num_lidar_pts and frame_id. Returns (frame ids (N,) or None, boxes (N, 7), categories (N,),
    num_lidar_pts (N,) int32, -1 when absent). Errors name the file, line and column."""
    path = Path(path)
    try:
        with open(path, newline="") as handle:
            reader = csv.DictReader(handle)
            header = reader.fieldnames or []
            missing = [c for c in CSV_COLUMNS if c not in header]
            if missing:
                raise ImportFormatError(
                    f"{path}: missing column '{missing[0]}' (header: {','.join(header)})"
                )
            values, categories, frames, lidar_pts = [], [], [], []
            for row in reader:
                line = reader.line_num
                if None in row or any(row[c] is None for c in header):
                    raise ImportFormatError(f"{path}, line {line}: expected {len(header)} fields")
                numbers = []
                for column in CSV_COLUMNS[1:]:
                    try:
                        number = float(row[column])
                    except ValueError:
                        raise ImportFormatError(
                            f"{path}, line {line}: column '{column}' is not a number: {row[column]!r}"
                        ) from None
                    if not np.isfinite(number):
                        raise ImportFormatError(
                            f"{path}, line {line}: column '{column}' is {row[column]}"
                        )
                    numbers.append(number)
                if min(numbers[3:6]) < 0:
                    raise ImportFormatError(f"{path}, line {line}: negative size")
                values.append(numbers)
                categories.append(row["category"])
                if "frame_id" in row:
                    check_id(row["frame_id"], f"{path}, line {line}, column 'frame_id'")
                frames.append(row.get("frame_id"))
                try:
                    count = int(row["num_lidar_pts"]) if "num_lidar_pts" in row else -1
                except ValueError:
                    raise ImportFormatError(
                        f"{path}, line {line}: column 'num_lidar_pts' is not an integer"
                    ) from None
                if not _INT32.min <= count <= _INT32.max:
                    raise ImportFormatError(
                        f"{path}, line {line}: column 'num_lidar_pts' = {count} is out of the int32 range"
                    )
                lidar_pts.append(count)
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise ImportFormatError(f"{path}: cannot read CSV ({error})") from None
    boxes = np.asarray(values, np.float64).reshape(-1, 7)
    boxes[:, 6] = wrap_angle(boxes[:, 6])
    frame_ids = np.asarray(frames, dtype=object) if "frame_id" in header else None
    return frame_ids, boxes, np.asarray(categories, dtype=object), np.asarray(lidar_pts, np.int32)


# ---------------------------------------------------------------------------------------------


def build_import(
    out: str | Path,
    source: JsonSource | CsvSource,
    samples: list[Sample],
    car_categories: tuple[str, ...] = DEFAULT_CAR_CATEGORIES,
    x_forward: bool = True,
    sensor: str = "nuscenes",
    progress: bool = True,
) -> BuildResult:
    """Stage body of `dali import nuscenes`: write FrameSet + boxes into `out`; returns counts
    (`progress`: a progress bar on stderr)."""

    def frames():
        for sample in samples:
            points, labeled = source.load(sample, car_categories, x_forward)
            table = None
            if labeled is not None:
                boxes, labels, lidar_pts = labeled
                plausibility.refuse_implausible(
                    boxes,
                    np.ones(len(boxes), bool),
                    f"the annotations of sample '{sample.frame_id}'",
                    [sample.frame_id] * len(boxes),
                )
                counts = (
                    count_points_in_boxes(points, boxes) if len(boxes) else np.zeros(0, np.int32)
                )
                table = BoxTable.from_arrays(
                    np.full(len(boxes), sample.frame_id, dtype=object),
                    boxes,
                    label=labels,
                    num_points=counts,
                    num_lidar_pts=lidar_pts,
                )
            yield sample.frame_id, points, table

    attrs = {
        "source_format": "nuscenes",
        "x_forward": bool(x_forward),
        "axes": "x forward, y left (rotated -90 deg about z from nuScenes LiDAR)"
        if x_forward
        else "nuScenes LiDAR: x right, y forward",
    }
    return write_imported(
        out,
        frames(),
        sensor,
        attrs,
        total=len(samples),
        progress=progress,
        notes=[
            attrs["axes"],
            "one key-frame sweep per frame (no multi-sweep accumulation); intensity / 255",
        ],
    )
