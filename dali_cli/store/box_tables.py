"""Box tables: `<dir>/boxes.parquet`, one row per box, columns frame_id, x, y, z, l, w, h, yaw
(float64, geometric centre, yaw CCW from +x), score (float32), label (string), num_points (int32)
plus optional extra columns: the `BoxTable` in memory, and its validated writer and reader
(what a box may plausibly be is labels/plausibility.py's). Re-exported by store/artifacts.py.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from dali_cli.store.artifact_errors import ArtifactError, TableValueError
from dali_cli.store.frame_ids import first_bad_name

BOXES_NAME = "boxes.parquet"
BOX_FIELDS = ("x", "y", "z", "l", "w", "h", "yaw")

_BASE_TYPES = {
    "frame_id": pa.string(),
    **{name: pa.float64() for name in BOX_FIELDS},
    "score": pa.float32(),
    "label": pa.string(),
    "num_points": pa.int32(),
}


_INT32 = np.iinfo(np.int32)


def int32_column(values, name: str, frame_id: np.ndarray | None = None) -> np.ndarray:
    """`values` as an `(N,)` int32 array, refusing (TableValueError naming the column, row and
    frame) anything a cast would change: values outside [-2**31, 2**31 - 1], NaN/inf, fractions,
    non-numbers. Used for num_points (from_arrays, with_columns, write and read) and by importers
    for their int32 columns (nuScenes num_lidar_pts)."""
    array = np.asarray(values)
    if array.dtype == np.int32:
        return array
    if array.dtype.kind == "b":
        return array.astype(np.int32)
    if array.dtype.kind not in "iuf":
        raise TableValueError(f"column '{name}': expected integers, got {array.dtype}")
    if array.dtype.kind == "f":
        bad = ~np.isfinite(array)
        bad[~bad] = array[~bad] != np.round(array[~bad])
    else:
        bad = np.zeros(array.shape, bool)
    with np.errstate(invalid="ignore"):
        bad |= (array < _INT32.min) | (array > _INT32.max)
    if bad.any():
        row = int(np.flatnonzero(bad.reshape(-1))[0])
        frame = (
            f" (frame '{frame_id[row]}')" if frame_id is not None and row < len(frame_id) else ""
        )
        raise TableValueError(
            f"column '{name}', row {row}{frame}: {array.reshape(-1)[row]} is not an int32 "
            f"(integers in {_INT32.min}..{_INT32.max})"
        )
    return array.astype(np.int32)


def _typed_column(name: str, values, frame_id: np.ndarray | None = None) -> np.ndarray:
    """`num_points` as int32, range-checked; every other column as given."""
    if name == "num_points":
        return int32_column(values, name, frame_id)
    return np.asarray(values)


@dataclass
class BoxTable:
    """Boxes of many frames as named numpy columns (see module docstring for the schema)."""

    columns: dict[str, np.ndarray]

    def __len__(self) -> int:
        return len(self.columns["frame_id"])

    def __getitem__(self, name: str) -> np.ndarray:
        return self.columns[name]

    @property
    def boxes(self) -> np.ndarray:
        """`(N, 7)` float64: x, y, z, l, w, h, yaw."""
        return np.stack([self.columns[name] for name in BOX_FIELDS], axis=1).reshape(-1, 7)

    @property
    def frame_id(self) -> np.ndarray:
        return self.columns["frame_id"]

    @property
    def extra_columns(self) -> list[str]:
        return [name for name in self.columns if name not in _BASE_TYPES]

    @classmethod
    def from_arrays(
        cls,
        frame_id: Sequence[str] | np.ndarray,
        boxes: np.ndarray,
        score: np.ndarray | None = None,
        label: str | Sequence[str] | np.ndarray = "Car",
        num_points: np.ndarray | None = None,
        **extra: np.ndarray,
    ) -> BoxTable:
        """Build from `(N,)` frame ids and `(N, 7)` boxes; defaults: score 1, label Car, 0 points."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        count = len(boxes)
        frame_id = np.asarray(frame_id, dtype=object).astype(str).reshape(-1)
        if frame_id.size != count:
            raise ValueError(f"{frame_id.size} frame ids for {count} boxes")
        if isinstance(label, str):
            label = np.full(count, label, dtype=object)
        columns = {
            "frame_id": frame_id.astype(object),
            **{name: boxes[:, i].copy() for i, name in enumerate(BOX_FIELDS)},
            "score": np.ones(count, np.float32) if score is None else np.asarray(score, np.float32),
            "label": np.asarray(label, dtype=object).reshape(-1),
            "num_points": np.zeros(count, np.int32)
            if num_points is None
            else int32_column(num_points, "num_points", frame_id),
        }
        for name, values in extra.items():
            columns[name] = np.asarray(values)
        for name, values in columns.items():
            if len(values) != count:
                raise ValueError(f"column '{name}' has {len(values)} rows, expected {count}")
        return cls(columns)

    @classmethod
    def empty(cls) -> BoxTable:
        return cls.from_arrays(np.zeros(0, dtype=str), np.zeros((0, 7)))

    def select(self, rows: np.ndarray) -> BoxTable:
        """Subset by boolean mask or integer indices."""
        return BoxTable({name: values[rows] for name, values in self.columns.items()})

    def with_columns(self, **columns: np.ndarray) -> BoxTable:
        merged = dict(self.columns)
        for name, values in columns.items():
            values = _typed_column(name, values, self.frame_id)
            if len(values) != len(self):
                raise ValueError(f"column '{name}' has {len(values)} rows, expected {len(self)}")
            merged[name] = values
        return BoxTable(merged)

    def rows_by_frame(self) -> dict[str, np.ndarray]:
        """frame_id → row indices `(k,)` int64, rows in table order."""
        if len(self) == 0:
            return {}
        ids = self.frame_id.astype(str)
        order = np.argsort(ids, kind="stable")
        sorted_ids = ids[order]
        starts = np.flatnonzero(np.r_[True, sorted_ids[1:] != sorted_ids[:-1]])
        stops = np.r_[starts[1:], len(ids)]
        return {str(sorted_ids[a]): order[a:b] for a, b in zip(starts, stops, strict=True)}

    def for_frame(self, frame_id: str) -> BoxTable:
        return self.select(np.flatnonzero(self.frame_id.astype(str) == str(frame_id)))

    @staticmethod
    def concat(tables: Sequence[BoxTable]) -> BoxTable:
        tables = [t for t in tables if t is not None]
        if not tables:
            return BoxTable.empty()
        names = list(tables[0].columns)
        for table in tables[1:]:
            if list(table.columns) != names:
                raise ValueError("cannot concatenate box tables with different columns")
        return BoxTable({n: np.concatenate([t.columns[n] for t in tables]) for n in names})

    def to_arrow(self) -> pa.Table:
        arrays, fields = [], []
        for name, values in self.columns.items():
            if name in _BASE_TYPES:
                values = _typed_column(name, values, self.frame_id)
                array = pa.array(values, type=_BASE_TYPES[name])
            elif values.dtype == object or values.dtype.kind == "U":
                # string columns stay strings when empty (pa.array([]) would be of type null,
                # which no reader accepts)
                array = pa.array(values.tolist(), type=pa.string() if len(values) == 0 else None)
            else:
                array = pa.array(values)
            arrays.append(array)
            fields.append(pa.field(name, array.type))
        return pa.Table.from_arrays(arrays, schema=pa.schema(fields))


def write_boxes(directory: str | Path, table: BoxTable) -> Path:
    """Write `<directory>/boxes.parquet`; validates values first (TableValueError, a ValueError,
    on NaN/inf boxes or scores, negative sizes, frame ids that cannot name a file, int32 columns
    out of range): what read_boxes would refuse is never written."""
    path = Path(directory) / BOXES_NAME
    problem = _value_problem(table)
    if problem is not None:  # what read_boxes would refuse is never written
        raise TableValueError(f"{path}: {problem}")
    arrow = table.to_arrow()
    _check_frame_ids(arrow.column("frame_id"), path, TableValueError)
    pq.write_table(arrow, path, compression="zstd")
    return path


def _check_frame_ids(ids: pa.ChunkedArray, path: Path, error=ArtifactError) -> None:
    """Raise `error` naming the file and the first row whose frame id cannot name a file; checks
    each distinct id once (a table has far fewer frames than rows)."""
    distinct = pc.unique(ids).to_pylist()
    bad = first_bad_name(distinct)
    if bad is not None:
        value = distinct[bad[0]]
        row = pc.index(ids, value).as_py() if value is not None else ids.to_pylist().index(None)
        raise error(f"{path}: row {row}: frame id {bad[1]}")


def _is_plain_type(arrow_type: pa.DataType) -> bool:
    return (
        pa.types.is_integer(arrow_type)
        or pa.types.is_floating(arrow_type)
        or pa.types.is_boolean(arrow_type)
        or pa.types.is_string(arrow_type)
        or pa.types.is_large_string(arrow_type)
    )


def check_frames_known(table: BoxTable, frame_ids, where: str) -> None:
    """ArtifactError naming `where` and the first frame id of `table` that `frame_ids` (a
    frame set's) does not hold: boxes of a frame that is not there are a mix-up of two sets."""
    known = set(frame_ids)
    unknown = [f for f in dict.fromkeys(table.frame_id.astype(str).tolist()) if f not in known]
    if unknown:
        raise ArtifactError(
            f"{where}: {len(unknown)} frame id(s) not in the frame set, the first '{unknown[0]}'"
        )


def read_boxes(directory: str | Path) -> BoxTable:
    """Read and validate `<directory>/boxes.parquet` (or a .parquet file path)."""
    from dali_cli.store.regular_files import SpecialFileError, UnreadableFileError, checked_size

    path = Path(directory)
    if path.is_dir() and path.suffix != ".parquet":
        path = path / BOXES_NAME
    try:  # a regular file within the table budget: a 4 GiB sparse file is refused by its size
        checked_size(path, "box table", "table")
    except (UnreadableFileError, SpecialFileError) as error:
        raise ArtifactError(str(error)) from None
    try:
        table = pq.read_table(path)
    except Exception as error:
        raise ArtifactError(f"{path}: cannot read Parquet ({error})") from None
    columns: dict[str, np.ndarray] = {}
    for name in table.column_names:
        arrow_type = table.schema.field(name).type
        if pa.types.is_null(arrow_type) and table.num_rows == 0 and name not in _BASE_TYPES:
            # an empty extra string column stored with Arrow type null (a writer with no value
            # to type it by): read it as the empty string column it is
            table = table.set_column(
                table.column_names.index(name), name, pa.array([], type=pa.string())
            )
            continue
        if not _is_plain_type(arrow_type):
            raise ArtifactError(f"{path}: column '{name}' has unsupported type {arrow_type}")
        if name in _BASE_TYPES:
            expected = _BASE_TYPES[name]
            compatible = (
                arrow_type == expected
                or (pa.types.is_string(expected) and pa.types.is_large_string(arrow_type))
                or (pa.types.is_floating(expected) and pa.types.is_floating(arrow_type))
                or (pa.types.is_integer(expected) and pa.types.is_integer(arrow_type))
            )
            if not compatible:
                raise ArtifactError(
                    f"{path}: column '{name}' must be {expected}, found {arrow_type}"
                )
    for name in _BASE_TYPES:
        if name not in table.column_names:
            raise ArtifactError(f"{path}: missing column '{name}'")
    for name in table.column_names:
        column = table.column(name)
        if name in _BASE_TYPES and column.null_count:
            raise ArtifactError(f"{path}: column '{name}' has {column.null_count} null values")
        if pa.types.is_string(column.type) or pa.types.is_large_string(column.type):
            values = np.asarray(column.to_pylist(), dtype=object)
        else:
            values = column.to_numpy()
        if name == "num_points":
            try:
                values = int32_column(values, name, columns.get("frame_id"))
            except TableValueError as error:
                raise ArtifactError(f"{path}: {error.message}") from None
        elif name in _BASE_TYPES and name not in ("frame_id", "label"):
            values = values.astype(_BASE_TYPES[name].to_pandas_dtype())
        columns[name] = values
    _check_frame_ids(table.column("frame_id"), path)
    result = BoxTable(columns)
    problem = _value_problem(result)
    if problem is not None:
        raise ArtifactError(f"{path}: {problem}")
    return result


def _value_problem(table: BoxTable) -> str | None:
    """The first row with NaN/inf box values, a negative size or a NaN/inf score, described
    with its frame; None when every row is fine (what a box may plausibly be:
    labels/plausibility.py, applied by the stages that read boxes)."""
    boxes = table.boxes
    score = np.asarray(table["score"], np.float64)
    checks = (
        (~np.isfinite(boxes).all(axis=1), "has NaN/inf box values"),
        ((boxes[:, 3:6] < 0).any(axis=1), "has a negative size"),
        (~np.isfinite(score), "has a NaN/inf score"),
    )
    for bad, problem in checks:
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            return f"row {row} (frame '{table.frame_id[row]}') {problem}"
    return None
