"""The on-disk data contract: FrameSets (Zarr v3 point clouds) and box tables (Parquet).

FrameSet: `<dir>/frames.zarr`, a Zarr v3 group with arrays
    points    float32 (N_total, 4)   x, y, z, intensity in the sensor frame (metres)
    offsets   int64   (F + 1,)       frame i is points[offsets[i]:offsets[i + 1]]
    frame_ids string  (F,)
and attrs `sensor`, `frame_convention` ("sensor"), `count`.

Box table: `<dir>/boxes.parquet`, one row per box, columns frame_id, x, y, z, l, w, h, yaw
(float64, geometric centre, yaw CCW from +x), score (float32), label (string), num_points (int32)
plus optional extra columns.

Every reader validates what it reads and raises ArtifactError naming the path and the problem.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

FRAMES_NAME = "frames.zarr"
BOXES_NAME = "boxes.parquet"
DEFAULT_CHUNK_POINTS = 2**21  # ~2 M points (32 MiB uncompressed) per chunk
BOX_FIELDS = ("x", "y", "z", "l", "w", "h", "yaw")


class ArtifactError(click.ClickException):
    """A missing or malformed artifact; the message names the path and the problem."""


# ---------------------------------------------------------------------------------------------
# FrameSet


class FrameSet:
    """Read access to a FrameSet directory. Reading one frame reads only the chunks it spans."""

    def __init__(self, directory: str | Path):
        import zarr

        self.directory = Path(directory)
        self.path = self.directory / FRAMES_NAME
        if not self.path.is_dir():
            raise ArtifactError(f"{self.path}: frame set not found (expected a Zarr group)")
        try:
            group = zarr.open_group(str(self.path), mode="r")
        except Exception as error:  # zarr raises several types for a broken group
            raise ArtifactError(f"{self.path}: cannot open Zarr group ({error})") from None
        for name in ("points", "offsets", "frame_ids"):
            if name not in group:
                raise ArtifactError(f"{self.path}: missing array '{name}'")
        self._points = group["points"]
        if self._points.dtype != np.float32 or self._points.ndim != 2 or self._points.shape[1] != 4:
            raise ArtifactError(
                f"{self.path}/points: expected float32 (N, 4), got {self._points.dtype} {self._points.shape}"
            )
        offsets = np.asarray(group["offsets"][:])
        if offsets.dtype != np.int64 or offsets.ndim != 1 or offsets.size < 1:
            raise ArtifactError(
                f"{self.path}/offsets: expected int64 (F + 1,), got {offsets.dtype} {offsets.shape}"
            )
        if offsets[0] != 0 or np.any(np.diff(offsets) < 0):
            raise ArtifactError(f"{self.path}/offsets: not monotone non-decreasing from 0")
        if offsets[-1] != self._points.shape[0]:
            raise ArtifactError(
                f"{self.path}/offsets: last offset {offsets[-1]} != number of points {self._points.shape[0]}"
            )
        frame_ids = [str(f) for f in np.asarray(group["frame_ids"][:]).tolist()]
        if len(frame_ids) != offsets.size - 1:
            raise ArtifactError(
                f"{self.path}/frame_ids: {len(frame_ids)} ids for {offsets.size - 1} frames"
            )
        if len(set(frame_ids)) != len(frame_ids):
            raise ArtifactError(f"{self.path}/frame_ids: duplicate frame ids")
        self.offsets = offsets
        self.frame_ids: list[str] = frame_ids
        self.attrs = dict(group.attrs)
        self.sensor: str = str(self.attrs.get("sensor", ""))
        self._index = {fid: i for i, fid in enumerate(frame_ids)}

    def __len__(self) -> int:
        return len(self.frame_ids)

    @property
    def num_points(self) -> int:
        return int(self.offsets[-1])

    def index_of(self, frame_id: str) -> int:
        try:
            return self._index[str(frame_id)]
        except KeyError:
            raise ArtifactError(f"{self.path}: no frame '{frame_id}'") from None

    def frame(self, index_or_id: int | str) -> np.ndarray:
        """Points of one frame, `(n, 4)` float32. Raises ArtifactError on NaN/inf values."""
        index = self.index_of(index_or_id) if isinstance(index_or_id, str) else int(index_or_id)
        start, stop = int(self.offsets[index]), int(self.offsets[index + 1])
        points = (
            np.asarray(self._points[start:stop]) if stop > start else np.zeros((0, 4), np.float32)
        )
        return self._checked(points, index)

    def _checked(self, points: np.ndarray, index: int) -> np.ndarray:
        if not np.isfinite(points).all():
            bad = int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])
            raise ArtifactError(
                f"{self.path}: frame '{self.frame_ids[index]}' point {bad} has NaN/inf values"
            )
        return points

    def iter_frames(self, indices: Sequence[int] | None = None) -> Iterator[tuple[str, np.ndarray]]:
        """Yield (frame_id, points) in order, reading contiguous runs of frames block-wise."""
        indices = range(len(self)) if indices is None else indices
        chunk = int(self._points.chunks[0])
        block_points = -(-max(DEFAULT_CHUNK_POINTS, chunk) // chunk) * chunk
        buffer_start, buffer = 0, np.zeros((0, 4), np.float32)
        for index in indices:
            start, stop = int(self.offsets[index]), int(self.offsets[index + 1])
            buffer_end = buffer_start + len(buffer)
            if start < buffer_start or stop > buffer_end:
                # read whole chunks, each once: a frame that runs past the buffer keeps the
                # buffer's tail and reads only the chunks after it
                keep_tail = buffer_start <= start < buffer_end
                read_start = buffer_end if keep_tail else (start // chunk) * chunk
                read_stop = max(-(-stop // chunk) * chunk, read_start + block_points)
                fresh = np.asarray(self._points[read_start : min(read_stop, self.num_points)])
                if keep_tail:
                    buffer = np.concatenate([buffer[start - buffer_start :], fresh])
                    buffer_start = start
                else:
                    buffer, buffer_start = fresh, read_start
            points = buffer[start - buffer_start : stop - buffer_start]
            yield self.frame_ids[index], self._checked(points, index)

    def load_all(self) -> tuple[np.ndarray, np.ndarray]:
        """All points `(N_total, 4)` float32 and offsets `(F + 1,)` int64, in memory."""
        points = np.asarray(self._points[:])
        if not np.isfinite(points).all():
            bad_point = int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])
            frame = int(np.searchsorted(self.offsets, bad_point, side="right") - 1)
            self._checked(points[self.offsets[frame] : self.offsets[frame + 1]], frame)
        return points, self.offsets.copy()


class FrameSetWriter:
    """Append frames one by one; points are flushed in whole chunks so memory stays bounded.

    Use as a context manager: `with FrameSetWriter(dir, sensor="kitti") as w: w.append(id, pts)`.
    The directory should be a stage's temporary output directory (see manifest.run_stage).
    """

    def __init__(
        self,
        directory: str | Path,
        sensor: str,
        attrs: dict | None = None,
        chunk_points: int = DEFAULT_CHUNK_POINTS,
        compress: bool = True,
    ):
        import zarr

        self.path = Path(directory) / FRAMES_NAME
        self._group = zarr.open_group(str(self.path), mode="w", zarr_format=3)
        # compress=False: raw float32 chunks (LiDAR coordinates shrink only ~8% with zstd, which
        # costs more CPU than the rest of a fast stage); readers need no change
        codecs = {} if compress else {"compressors": None}
        # point chunks are never all zeros: skip zarr's costly "is this chunk empty?" scan
        # (about 3/4 of the CPU time of writing uncompressed chunks)
        self._points = self._group.create_array(
            "points",
            shape=(0, 4),
            chunks=(chunk_points, 4),
            dtype="float32",
            config={"write_empty_chunks": True},
            **codecs,
        )
        self._chunk = chunk_points
        self._pending: list[np.ndarray] = []
        self._pending_count = 0
        self._written = 0
        self._offsets = [0]
        self._frame_ids: list[str] = []
        self._seen: set[str] = set()  # duplicate check in O(1) (a list scan is O(F) per frame)
        self._attrs = {"sensor": sensor, "frame_convention": "sensor", **(attrs or {})}
        self._closed = False

    def append(self, frame_id: str, points: np.ndarray) -> None:
        """Add one frame; `points` is `(n, 4)` (x, y, z, intensity), cast to float32."""
        points = np.asarray(points, dtype=np.float32)
        if points.ndim != 2 or points.shape[1] != 4:
            raise ValueError(f"frame '{frame_id}': points must be (n, 4), got {points.shape}")
        if not np.isfinite(points).all():
            raise ValueError(f"frame '{frame_id}': points contain NaN/inf")
        frame_id = str(frame_id)
        if frame_id in self._seen:
            raise ValueError(f"frame '{frame_id}' appended twice")
        self._frame_ids.append(frame_id)
        self._seen.add(frame_id)
        self._offsets.append(self._offsets[-1] + len(points))
        if len(points):
            self._pending.append(points)
            self._pending_count += len(points)
        if self._pending_count >= self._chunk:
            self._flush(final=False)

    def _flush(self, final: bool) -> None:
        if not self._pending:
            return
        data = np.concatenate(self._pending)
        take = len(data) if final else (len(data) // self._chunk) * self._chunk
        if take:
            self._points.resize((self._written + take, 4))
            self._points[self._written : self._written + take] = data[:take]
            self._written += take
        rest = data[take:]
        self._pending = [rest] if len(rest) else []
        self._pending_count = len(rest)

    def close(self) -> None:
        if self._closed:
            return
        self._flush(final=True)
        self._group.create_array("offsets", data=np.asarray(self._offsets, dtype=np.int64))
        # dtype=str is Zarr's variable-length UTF-8 string type (stable in the v3 spec)
        ids = self._group.create_array("frame_ids", shape=(len(self._frame_ids),), dtype=str)
        if self._frame_ids:
            ids[:] = np.asarray(self._frame_ids, dtype=object)
        self._group.attrs.update({**self._attrs, "count": len(self._frame_ids)})
        self._closed = True

    def __enter__(self) -> FrameSetWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()

    @property
    def count(self) -> int:
        return len(self._frame_ids)

    @property
    def num_points(self) -> int:
        return self._offsets[-1]


def write_frameset(
    directory: str | Path,
    frames: Iterable[tuple[str, np.ndarray]],
    sensor: str,
    attrs: dict | None = None,
    chunk_points: int = DEFAULT_CHUNK_POINTS,
) -> int:
    """Write (frame_id, points) pairs as a FrameSet; returns the number of frames."""
    with FrameSetWriter(directory, sensor, attrs, chunk_points) as writer:
        for frame_id, points in frames:
            writer.append(frame_id, points)
    return writer.count


# ---------------------------------------------------------------------------------------------
# Box tables

_BASE_TYPES = {
    "frame_id": pa.string(),
    **{name: pa.float64() for name in BOX_FIELDS},
    "score": pa.float32(),
    "label": pa.string(),
    "num_points": pa.int32(),
}


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
            else np.asarray(num_points, np.int32),
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
            values = np.asarray(values)
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
                array = pa.array(values, type=_BASE_TYPES[name])
            elif values.dtype == object:
                # object columns hold strings; typed explicitly, else an empty one is written as
                # pyarrow's null type, which read_boxes rejects (an empty ppcg table, issue 17)
                array = pa.array(values.tolist(), type=pa.string() if len(values) == 0 else None)
            else:
                array = pa.array(values)
            arrays.append(array)
            fields.append(pa.field(name, array.type))
        return pa.Table.from_arrays(arrays, schema=pa.schema(fields))


def write_boxes(directory: str | Path, table: BoxTable) -> Path:
    """Write `<directory>/boxes.parquet`; validates values first (ValueError on NaN/inf)."""
    boxes = table.boxes
    if not np.isfinite(boxes).all():
        row = int(np.flatnonzero(~np.isfinite(boxes).all(axis=1))[0])
        raise ValueError(f"box row {row} (frame '{table.frame_id[row]}') has NaN/inf values")
    path = Path(directory) / BOXES_NAME
    pq.write_table(table.to_arrow(), path, compression="zstd")
    return path


def _is_plain_type(arrow_type: pa.DataType) -> bool:
    return (
        pa.types.is_integer(arrow_type)
        or pa.types.is_floating(arrow_type)
        or pa.types.is_boolean(arrow_type)
        or pa.types.is_string(arrow_type)
        or pa.types.is_large_string(arrow_type)
    )


def read_boxes(directory: str | Path) -> BoxTable:
    """Read and validate `<directory>/boxes.parquet` (or a .parquet file path)."""
    path = Path(directory)
    if path.is_dir():
        path = path / BOXES_NAME
    if not path.is_file():
        raise ArtifactError(f"{path}: box table not found")
    try:
        table = pq.read_table(path)
    except Exception as error:
        raise ArtifactError(f"{path}: cannot read Parquet ({error})") from None
    columns: dict[str, np.ndarray] = {}
    for name in table.column_names:
        arrow_type = table.schema.field(name).type
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
        if name in _BASE_TYPES and name not in ("frame_id", "label"):
            values = values.astype(_BASE_TYPES[name].to_pandas_dtype())
        columns[name] = values
    result = BoxTable(columns)
    boxes = result.boxes
    finite = np.isfinite(boxes).all(axis=1)
    if not finite.all():
        row = int(np.flatnonzero(~finite)[0])
        raise ArtifactError(
            f"{path}: row {row} (frame '{result.frame_id[row]}') has NaN/inf box values"
        )
    negative = (boxes[:, 3:6] < 0).any(axis=1)
    if negative.any():
        row = int(np.flatnonzero(negative)[0])
        raise ArtifactError(
            f"{path}: row {row} (frame '{result.frame_id[row]}') has a negative size"
        )
    return result
