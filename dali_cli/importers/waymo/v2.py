"""Waymo Open Dataset v2: one Parquet file per segment and component
(`ROOT[/SPLIT]/<component>/<segment>.parquet`), joined on the key columns. Column names are the
dataset's own (waymo_open_dataset/v2/perception/*.py: `key.*` and
`[ComponentClass].field.subfield`). Only the columns dali needs are read, and the lidar
component (the large one) one row group at a time.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from dali_cli.importers.waymo.frame import (
    TOP,
    LaserCalibration,
    LaserScan,
    WaymoFormatError,
    WaymoFrame,
)

SEGMENT = "key.segment_context_name"
TIMESTAMP = "key.frame_timestamp_micros"
LASER = "key.laser_name"
COMPONENTS = ("lidar", "lidar_calibration", "lidar_box", "vehicle_pose", "lidar_pose")
REQUIRED = ("lidar", "lidar_calibration")


def _range_image_columns(component: str, ret: int) -> tuple[str, str]:
    prefix = f"[{component}].range_image_return{ret}"
    return f"{prefix}.values", f"{prefix}.shape"


CALIBRATION_COLUMNS = [
    LASER,
    "[LiDARCalibrationComponent].extrinsic.transform",
    "[LiDARCalibrationComponent].beam_inclination.min",
    "[LiDARCalibrationComponent].beam_inclination.max",
    "[LiDARCalibrationComponent].beam_inclination.values",
]
VEHICLE_POSE_COLUMNS = [TIMESTAMP, "[VehiclePoseComponent].world_from_vehicle.transform"]
BOX = "[LiDARBoxComponent]"
BOX_COLUMNS = [
    TIMESTAMP,
    *(f"{BOX}.box.center.{a}" for a in "xyz"),
    *(f"{BOX}.box.size.{a}" for a in "xyz"),
    f"{BOX}.box.heading",
    f"{BOX}.type",
    f"{BOX}.num_lidar_points_in_box",
]


def component_path(root: Path, component: str, segment: str) -> Path:
    return root / component / f"{segment}.parquet"


def list_segments(root: Path) -> list[str]:
    """Segment names that have a lidar component file under `root`."""
    return sorted(p.stem for p in (root / "lidar").glob("*.parquet"))


def _read_arrow(path: Path, columns: list[str], segment: str):
    """The given columns of a component file (an Arrow table); errors name the file."""
    try:
        schema = pq.read_schema(path)
    except Exception as error:
        raise WaymoFormatError(f"{path}: not a Parquet file ({error})") from None
    missing = [c for c in columns if c not in schema.names]
    if missing:
        raise WaymoFormatError(f"{path} (segment {segment}): missing columns {missing}")
    return pq.read_table(path, columns=columns)


def _read(path: Path, columns: list[str], segment: str) -> dict[str, list]:
    """The given columns of a small component file as Python lists."""
    return _read_arrow(path, columns, segment).to_pydict()


class ListColumn:
    """A list<number> column of an Arrow table, row slices as numpy views (no Python lists:
    a TOP range image has 678,400 values). Accepts variable-size lists (`values`:
    list<float>) and fixed-size lists (`shape`: list<int32, 3>, transforms: list<float, 16>),
    the types the dataset's component definitions and its files use."""

    def __init__(self, table, name: str):
        column = table.column(name).combine_chunks()
        self.valid = ~np.asarray(column.is_null().to_numpy(zero_copy_only=False), bool)
        if pa.types.is_fixed_size_list(column.type):
            # no offsets buffer: row r holds values[(offset + r) * size, (offset + r + 1) * size)
            size = column.type.list_size
            self.offsets = (np.arange(len(column) + 1, dtype=np.int64) + column.offset) * size
        elif pa.types.is_list(column.type) or pa.types.is_large_list(column.type):
            self.offsets = np.asarray(column.offsets.to_numpy(), np.int64)
        else:
            raise WaymoFormatError(
                f"column {name}: expected a list of numbers, found {column.type}"
            )
        self.values = column.values.to_numpy(zero_copy_only=False)

    def __getitem__(self, row: int):
        if not self.valid[row]:
            return None
        return self.values[self.offsets[row] : self.offsets[row + 1]]


def _matrix(values, shape, where: str) -> np.ndarray | None:
    if values is None or shape is None:
        return None
    data = np.asarray(values, np.float32)
    if len(shape) != 3 or int(np.prod(shape)) != data.size:
        raise WaymoFormatError(f"{where}: {data.size} range image values for shape {shape}")
    return data.reshape(shape)


def read_calibrations(root: Path, segment: str) -> dict[int, LaserCalibration]:
    path = component_path(root, "lidar_calibration", segment)
    if not path.is_file():
        raise WaymoFormatError(f"segment {segment}: component lidar_calibration missing ({path})")
    table = _read(path, CALIBRATION_COLUMNS, segment)
    calibrations = {}
    for name, transform, low, high, values in zip(*table.values(), strict=True):
        extrinsic = np.asarray(transform, np.float64)
        if extrinsic.size != 16:
            raise WaymoFormatError(f"{path}: laser {name}: extrinsic has {extrinsic.size} values")
        inclinations = None if not values else np.asarray(values, np.float64)
        calibrations[int(name)] = LaserCalibration(
            int(name), extrinsic.reshape(4, 4), inclinations, float(low), float(high)
        )
    return calibrations


def read_vehicle_poses(root: Path, segment: str) -> dict[int, np.ndarray]:
    path = component_path(root, "vehicle_pose", segment)
    if not path.is_file():
        return {}
    table = _read(path, VEHICLE_POSE_COLUMNS, segment)
    return {
        int(t): np.asarray(m, np.float64).reshape(4, 4)
        for t, m in zip(table[TIMESTAMP], table[VEHICLE_POSE_COLUMNS[1]], strict=True)
    }


def read_pixel_poses(root: Path, segment: str, timestamps: set[int]) -> dict[int, np.ndarray]:
    """TOP's per-pixel poses (H, W, 6) by timestamp (only the frames asked for)."""
    path = component_path(root, "lidar_pose", segment)
    if not path.is_file():
        return {}
    values, shape = _range_image_columns("LiDARPoseComponent", 1)
    table = _read_arrow(path, [TIMESTAMP, LASER, values, shape], segment)
    stamps, lasers = table.column(TIMESTAMP).to_numpy(), table.column(LASER).to_numpy()
    value_rows, shape_rows = ListColumn(table, values), ListColumn(table, shape)
    poses = {}
    for row, (t, laser) in enumerate(zip(stamps, lasers, strict=True)):
        if int(laser) == TOP and int(t) in timestamps:
            where = f"segment {segment}, timestamp {t}, TOP pose"
            poses[int(t)] = _matrix(value_rows[row], shape_rows[row], where)
    return poses


def read_boxes(root: Path, segment: str) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """timestamp → (boxes (N, 7) vehicle frame, types (N,), num_lidar_points_in_box (N,))."""
    path = component_path(root, "lidar_box", segment)
    if not path.is_file():
        return {}
    table = _read(path, BOX_COLUMNS, segment)
    columns = [np.asarray(table[c]) for c in BOX_COLUMNS]
    boxes = np.stack(columns[1:8], axis=1).astype(np.float64)
    grouped = defaultdict(list)
    for row, t in enumerate(columns[0]):
        grouped[int(t)].append(row)
    return {
        t: (boxes[rows], columns[8][rows].astype(np.int64), columns[9][rows].astype(np.int64))
        for t, rows in grouped.items()
    }


def read_segment(
    root: Path, segment: str, returns: int = 1, lidars: str = "top", every: int = 1
) -> Iterator[WaymoFrame]:
    """The frames of one v2 segment, in timestamp order (every `every`-th)."""
    path = component_path(root, "lidar", segment)
    calibrations = read_calibrations(root, segment)
    columns = [TIMESTAMP, LASER]
    for ret in range(1, returns + 1):
        columns += list(_range_image_columns("LiDARComponent", ret))
    try:
        lidar = pq.ParquetFile(path)
    except Exception as error:
        raise WaymoFormatError(f"{path}: not a Parquet file ({error})") from None
    missing = [c for c in columns if c not in lidar.schema_arrow.names]
    if missing:
        raise WaymoFormatError(f"{path} (segment {segment}): missing columns {missing}")
    keys = lidar.read(columns=[TIMESTAMP, LASER]).to_pydict()
    wanted_laser = [lidars == "all" or int(n) == TOP for n in keys[LASER]]
    stamps = sorted({int(t) for t, w in zip(keys[TIMESTAMP], wanted_laser, strict=True) if w})
    chosen = set(stamps[::every])
    expected = defaultdict(int)
    for t, w in zip(keys[TIMESTAMP], wanted_laser, strict=True):
        if w and int(t) in chosen:
            expected[int(t)] += 1
    poses = read_vehicle_poses(root, segment)
    pixel_poses = read_pixel_poses(root, segment, chosen)
    boxes = read_boxes(root, segment)
    pending: dict[int, list[LaserScan]] = defaultdict(list)
    ready: dict[int, WaymoFrame] = {}
    image_columns = [_range_image_columns("LiDARComponent", r) for r in range(1, returns + 1)]
    for group in range(lidar.num_row_groups):
        arrow = lidar.read_row_group(group, columns=columns)
        table = {name: arrow.column(name).to_numpy() for name in (TIMESTAMP, LASER)}
        lists = {name: ListColumn(arrow, name) for pair in image_columns for name in pair}
        for row in range(len(table[TIMESTAMP])):
            t, laser = int(table[TIMESTAMP][row]), int(table[LASER][row])
            if t not in chosen or not (lidars == "all" or laser == TOP):
                continue
            where = f"segment {segment}, timestamp {t}, laser {laser}"
            images = [
                _matrix(lists[v][row], lists[s][row], f"{where}, return {ret}")
                for ret, (v, s) in enumerate(image_columns, start=1)
            ]
            pose = pixel_poses.get(t) if laser == TOP else None
            pending[t].append(LaserScan(laser, images + [None] * (2 - len(images)), pose))
            if len(pending[t]) == expected[t]:
                frame_boxes = boxes.get(t, (np.zeros((0, 7)), np.zeros(0), np.zeros(0)))
                ready[t] = WaymoFrame(
                    segment, t, poses.get(t), calibrations, pending.pop(t), *frame_boxes
                )
        for t in sorted(ready):  # frames complete after this row group, in time order
            yield ready.pop(t)
    if pending:
        t = min(pending)
        raise WaymoFormatError(f"segment {segment}, timestamp {t}: range images incomplete")
