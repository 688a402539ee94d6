"""A frame set's sequence table, `sequence.parquet`: one row per scan, its time and poses.

This module owns the table; every importer writes it and every stage reads it through here.

Columns (R in 0..2, C in 0..3; a pose is 3 x 4 row-major, x_first = pose @ [x_scan, 1]):

- frame_id (str, unique) and index (int64, the scan's index in its recording);
- time_s (float64, optional): the scan's timestamp (KITTI odometry's times.txt);
- camera_pose_RC (float64, optional): camera 0 of the scan in camera 0 of the recording's scan 0,
  as the KITTI odometry dataset gives it (poses.txt / poses/NN.txt);
- lidar_pose_RC (float64, whenever it can be derived): the scan's LiDAR frame in the LiDAR frame
  of the recording's first scan (kitti-raw --poses: the first imported scan, from OXTS;
  kitti-odometry with calib.txt: inv(Tr) @ camera_pose @ Tr, relative to scan 0 of the sequence
  even when the import starts later). `dali track-pseudo` needs it;
- recording (str, optional): which recording (drive) the scan belongs to. `dali merge` writes the
  input's NAME; poses of different recordings are in different world frames and never mix.
  Without it the whole table is one recording.

A pose group is all or nothing: a table with some of a group's 12 columns is malformed. In a
merged table a recording without a group holds nulls there.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa

from dali_cli.runtime.errors import StageError

SEQUENCE_TABLE = "sequence.parquet"
TIME_COLUMN = "time_s"
RECORDING_COLUMN = "recording"
LIDAR_POSE_COLUMNS = tuple(f"lidar_pose_{row}{col}" for row in range(3) for col in range(4))
CAMERA_POSE_COLUMNS = tuple(f"camera_pose_{row}{col}" for row in range(3) for col in range(4))
POSE_GROUPS = {"lidar_pose": LIDAR_POSE_COLUMNS, "camera_pose": CAMERA_POSE_COLUMNS}


class SequenceError(StageError):
    """A missing or malformed sequence table; the message names the file and the field."""


def lidar_from_camera_poses(camera_poses: np.ndarray, velo_to_cam: np.ndarray) -> np.ndarray:
    """`(n, 4, 4)` LiDAR poses from KITTI odometry camera-0 poses `(n, 3 or 4, 4)` and the
    velodyne -> camera 0 transform `Tr` `(3 or 4, 4)` of calib.txt: inv(Tr) @ P_i @ Tr (a point
    of scan i's LiDAR frame -> camera 0 of scan i -> camera 0 of scan 0 -> LiDAR of scan 0, as
    SemanticKITTI's generate_sequential.py does)."""
    tr = homogeneous(np.asarray(velo_to_cam, np.float64)[None])[0]
    poses = homogeneous(np.asarray(camera_poses, np.float64))
    return np.linalg.inv(tr) @ poses @ tr


def homogeneous(poses: np.ndarray) -> np.ndarray:
    """`(n, 4, 4)` of `(n, 3, 4)` or `(n, 4, 4)` poses."""
    out = np.tile(np.eye(4), (len(poses), 1, 1))
    out[:, :3, :] = poses[:, :3, :]
    return out


def sequence_table(
    frame_ids: list[str],
    *,
    index: np.ndarray | None = None,
    time_s: np.ndarray | None = None,
    camera_poses: np.ndarray | None = None,
    lidar_poses: np.ndarray | None = None,
) -> pa.Table:
    """The table of `frame_ids` (index: each id's integer value when omitted) with the columns
    given: `time_s` (n,), `camera_poses` / `lidar_poses` (n, 3 or 4, 4)."""
    n = len(frame_ids)
    if index is None:
        index = [int(f) if f.isdigit() else i for i, f in enumerate(frame_ids)]
    columns = {
        "frame_id": pa.array(frame_ids, pa.string()),
        "index": pa.array(np.asarray(index, np.int64)),
    }
    if time_s is not None:
        columns[TIME_COLUMN] = pa.array(np.asarray(time_s, np.float64).reshape(n))
    for names, poses in ((CAMERA_POSE_COLUMNS, camera_poses), (LIDAR_POSE_COLUMNS, lidar_poses)):
        if poses is not None:
            rows = np.asarray(poses, np.float64)[:, :3, :].reshape(n, 12)
            columns.update({name: pa.array(rows[:, i]) for i, name in enumerate(names)})
    return pa.table(columns)


def write_sequence(
    directory: str | Path,
    frame_ids: list[str],
    lidar_poses: np.ndarray | None = None,
    **columns,
) -> Path:
    """Write `directory/sequence.parquet` of `frame_ids`, their `(n, 4, 4)` LiDAR poses and the
    other columns of sequence_table (index, time_s, camera_poses)."""
    return write_table(directory, sequence_table(frame_ids, lidar_poses=lidar_poses, **columns))


def write_table(directory: str | Path, table: pa.Table) -> Path:
    import pyarrow.parquet as pq

    path = Path(directory) / SEQUENCE_TABLE
    pq.write_table(table, path)
    return path


def read_sequence(directory: str | Path) -> pa.Table:
    """`directory/sequence.parquet`, checked: frame_id strings, unique; index integers; time_s
    and every present pose group numeric and complete (nulls only where a merged recording
    lacks the group). SequenceError naming the file and the field otherwise."""
    import pyarrow.parquet as pq

    path = Path(directory) / SEQUENCE_TABLE
    if not path.is_file():
        raise SequenceError(f"{path}: no sequence table (scan poses) in this frame set")
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowException) as error:
        raise SequenceError(f"{path}: cannot read Parquet ({error})") from None
    legacy = [f"pose_{row}{col}" for row in range(3) for col in range(4)]
    if legacy[0] in table.column_names and CAMERA_POSE_COLUMNS[0] not in table.column_names:
        # kitti-odometry imports made before the one schema: pose_RC was the camera-0 pose
        table = table.rename_columns(
            [
                dict(zip(legacy, CAMERA_POSE_COLUMNS, strict=True)).get(n, n)
                for n in table.column_names
            ]
        )
    names = table.column_names
    for name in ("frame_id", "index"):
        if name not in names:
            raise SequenceError(f"{path}: column '{name}' missing")
    if not pa.types.is_string(table.schema.field("frame_id").type):
        raise SequenceError(
            f"{path}: column 'frame_id' is {table.schema.field('frame_id').type}, not strings"
        )
    frame_ids = table.column("frame_id").to_pylist()
    if None in frame_ids:
        raise SequenceError(f"{path}: column 'frame_id' has a null at row {frame_ids.index(None)}")
    if len(set(frame_ids)) != len(frame_ids):
        seen = set()
        twice = next(f for f in frame_ids if f in seen or seen.add(f))
        raise SequenceError(f"{path}: field 'frame_id': frame '{twice}' appears twice")
    if not pa.types.is_integer(table.schema.field("index").type):
        raise SequenceError(
            f"{path}: column 'index' is {table.schema.field('index').type}, not integers"
        )
    numeric = [TIME_COLUMN] if TIME_COLUMN in names else []
    for group, columns in POSE_GROUPS.items():
        present = [name for name in columns if name in names]
        if present and len(present) < len(columns):
            missing = next(name for name in columns if name not in names)
            raise SequenceError(
                f"{path}: column '{missing}' missing (the {group} group is partial)"
            )
        numeric += present
    for name in numeric:
        kind = table.schema.field(name).type
        if not (pa.types.is_floating(kind) or pa.types.is_integer(kind)):
            raise SequenceError(f"{path}: column '{name}' is {kind}, not numbers")
        values = table.column(name).to_numpy(zero_copy_only=False).astype(np.float64)
        bad = np.flatnonzero(np.isinf(values) | (np.isnan(values) & ~null_mask(table, name)))
        if len(bad):
            raise SequenceError(
                f"{path}: column '{name}' is NaN/inf for frame '{frame_ids[bad[0]]}'"
            )
    return table


def null_mask(table: pa.Table, name: str) -> np.ndarray:
    return table.column(name).is_null().to_numpy(zero_copy_only=False)


def read_lidar_poses(directory: str | Path, frame_ids: list[str]) -> np.ndarray:
    """`(n, 4, 4)` float64 LiDAR pose of each of `frame_ids` from `directory/sequence.parquet`.

    SequenceError (naming the file and the field) when the table is missing or malformed, lacks
    the lidar_pose columns or a frame, has no LiDAR pose for a frame, or a pose's rotation is not
    a rotation."""
    path = Path(directory) / SEQUENCE_TABLE
    table = read_sequence(directory)
    if LIDAR_POSE_COLUMNS[0] not in table.column_names:
        why = ""
        if CAMERA_POSE_COLUMNS[0] in table.column_names:
            why = " (camera poses only: import with calib.txt to derive the LiDAR poses)"
        raise SequenceError(f"{path}: column '{LIDAR_POSE_COLUMNS[0]}' missing{why}")
    rows = rows_of(table, path, frame_ids)
    poses = np.tile(np.eye(4), (len(frame_ids), 1, 1))
    for i, name in enumerate(LIDAR_POSE_COLUMNS):
        if null_mask(table, name)[rows].any():
            frame = frame_ids[int(np.flatnonzero(null_mask(table, name)[rows])[0])]
            raise SequenceError(
                f"{path}: column '{name}' is null for frame '{frame}' (no LiDAR pose)"
            )
        poses[:, i // 4, i % 4] = table.column(name).to_numpy(zero_copy_only=False)[rows]
    rotation = poses[:, :3, :3]
    error = np.abs(rotation @ rotation.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((error > 1e-3) | (np.linalg.det(rotation) < 0))
    if len(bad):
        raise SequenceError(
            f"{path}: columns 'lidar_pose_00'..'lidar_pose_22' of frame '{frame_ids[bad[0]]}' "
            "are not a rotation"
        )
    return poses


def rows_of(table: pa.Table, path: Path, frame_ids: list[str]) -> np.ndarray:
    row_of = {f: i for i, f in enumerate(table.column("frame_id").to_pylist())}
    missing = [f for f in frame_ids if f not in row_of]
    if missing:
        raise SequenceError(f"{path}: field 'frame_id': no pose for frame '{missing[0]}'")
    return np.array([row_of[f] for f in frame_ids], np.int64)


def read_recordings(directory: str | Path, frame_ids: list[str]) -> list[str]:
    """The recording of each of `frame_ids` (the `recording` column; '' for all when the table
    has none: one recording). The table must hold every frame (read_lidar_poses checks)."""
    table = read_sequence(directory)
    if RECORDING_COLUMN not in table.column_names:
        return [""] * len(frame_ids)
    values = table.column(RECORDING_COLUMN).to_pylist()
    path = Path(directory) / SEQUENCE_TABLE
    recordings = [values[row] for row in rows_of(table, path, frame_ids)]
    if None in recordings:
        frame = frame_ids[recordings.index(None)]
        raise SequenceError(f"{path}: column '{RECORDING_COLUMN}' is null for frame '{frame}'")
    return [str(r) for r in recordings]


def merge_sequences(parts: list[tuple[str, pa.Table]], rename) -> pa.Table:
    """One table of the inputs' checked tables `(name, table)`: frame ids renamed by
    `rename(name, frame_id)`, recording = the input's name (`name-<recording>` when the input
    was itself merged). Columns: the union; a recording lacking time_s or a pose group holds
    nulls there (read_lidar_poses then names the frame without a LiDAR pose)."""
    tables = []
    for name, table in parts:
        ids = [rename(name, f) for f in table.column("frame_id").to_pylist()]
        table = table.set_column(0, "frame_id", pa.array(ids, pa.string()))
        if RECORDING_COLUMN in table.column_names:
            inner = table.column(RECORDING_COLUMN).to_pylist()
            recording = [rename(name, r) if r else name for r in inner]
            table = table.drop_columns([RECORDING_COLUMN])
        else:
            recording = [name] * len(table)
        table = table.set_column(
            table.column_names.index("index"), "index", table.column("index").cast(pa.int64())
        )
        tables.append(table.append_column(RECORDING_COLUMN, pa.array(recording, pa.string())))
    return pa.concat_tables(tables, promote_options="default")


def read_sequence_if_any(directory: str | Path) -> pa.Table | None:
    """`directory/sequence.parquet` checked (read_sequence), None when there is none."""
    return read_sequence(directory) if (Path(directory) / SEQUENCE_TABLE).is_file() else None


def scan_order(
    frame_ids: list[str], table: pa.Table | None, fallback_recordings: list[str]
) -> tuple[np.ndarray, list[str]]:
    """`(n,)` int64 index and the recording of each of `frame_ids`: the table's `index` and
    `recording` where it has the frame (and the column); else `fallback_recordings` (a merged
    set's names) and the integer the frame id ends with (after a `NAME-` prefix), or the frame
    id's rank in sorted order."""
    rows: dict[str, int] = {}
    index_column, recording_column = [], []
    if table is not None:
        rows = {f: i for i, f in enumerate(table.column("frame_id").to_pylist())}
        index_column = table.column("index").to_pylist()
        if RECORDING_COLUMN in table.column_names:
            recording_column = table.column(RECORDING_COLUMN).to_pylist()
    rank = {f: i for i, f in enumerate(sorted(frame_ids))}
    index = np.zeros(len(frame_ids), np.int64)
    recordings = list(fallback_recordings)
    for position, frame_id in enumerate(frame_ids):
        row = rows.get(frame_id)
        tail = frame_id.rpartition("-")[2]
        if row is not None:
            index[position] = index_column[row]
        else:
            index[position] = int(tail) if tail.isdigit() else rank[frame_id]
        if row is not None and recording_column and recording_column[row] is not None:
            recordings[position] = str(recording_column[row])
    return index, recordings


def registered_table(
    frame_ids: list[str],
    index: np.ndarray,
    recordings: list[str],
    lidar_poses: np.ndarray,
    source: pa.Table | None = None,
) -> pa.Table:
    """The sequence table of `frame_ids` with `(n, 4, 4)` `lidar_poses` (e.g. from scan
    registration), `(n,)` index, and recording (the column only when some recording is named);
    `source` (the frame set's own table, or None): its time_s and camera poses are kept for the
    frames it holds (nulls for the others), its LiDAR poses replaced."""
    table = sequence_table(frame_ids, index=index, lidar_poses=lidar_poses)
    if source is not None:
        rows = {f: i for i, f in enumerate(source.column("frame_id").to_pylist())}
        at = pa.array([rows.get(f) for f in frame_ids], pa.int64())
        for name in (TIME_COLUMN, *CAMERA_POSE_COLUMNS):
            if name in source.column_names:
                values = source.column(name).cast(pa.float64()).take(at)
                table = table.append_column(name, values)
    if any(recordings):
        table = table.append_column(RECORDING_COLUMN, pa.array(recordings, pa.string()))
    return table
