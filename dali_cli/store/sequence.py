"""A frame set's sequence table, `sequence.parquet`: one row per scan with its pose.

Columns: frame_id (str), index (int64, the scan's index in its recording), lidar_pose_RC
(float64, R in 0..2, C in 0..3: the 3 x 4 row-major pose of the scan's LiDAR frame in the LiDAR
frame of the recording's first scan, x_first = pose @ [x_scan, 1]).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa

from dali_cli.runtime.errors import StageError

SEQUENCE_TABLE = "sequence.parquet"
LIDAR_POSE_COLUMNS = tuple(f"lidar_pose_{row}{col}" for row in range(3) for col in range(4))


class SequenceError(StageError):
    """A missing or malformed sequence table; the message names the file and the field."""


def write_sequence(directory: str | Path, frame_ids: list[str], poses: np.ndarray) -> Path:
    """Write `directory/sequence.parquet` of `frame_ids` and their `(n, 4, 4)` LiDAR poses."""
    import pyarrow.parquet as pq

    path = Path(directory) / SEQUENCE_TABLE
    rows = np.asarray(poses, np.float64)[:, :3, :].reshape(len(frame_ids), 12)  # (n, 12)
    columns = {
        "frame_id": pa.array(frame_ids, pa.string()),
        "index": pa.array([int(f) if f.isdigit() else i for i, f in enumerate(frame_ids)]),
        **{name: pa.array(rows[:, i]) for i, name in enumerate(LIDAR_POSE_COLUMNS)},
    }
    pq.write_table(pa.table(columns), path)
    return path


def read_lidar_poses(directory: str | Path, frame_ids: list[str]) -> np.ndarray:
    """`(n, 4, 4)` float64 LiDAR pose of each of `frame_ids` from `directory/sequence.parquet`.

    SequenceError (naming the file and the field) when the table is missing, lacks a pose
    column or a frame, holds NaN/inf, or a pose's rotation is not a rotation."""
    import pyarrow.parquet as pq

    path = Path(directory) / SEQUENCE_TABLE
    if not path.is_file():
        raise SequenceError(f"{path}: no sequence table (scan poses) in this frame set")
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowException) as error:
        raise SequenceError(f"{path}: cannot read Parquet ({error})") from None
    for name in ("frame_id", *LIDAR_POSE_COLUMNS):
        if name not in table.column_names:
            raise SequenceError(f"{path}: column '{name}' missing")
    row_of = {str(f): i for i, f in enumerate(table.column("frame_id").to_pylist())}
    missing = [f for f in frame_ids if f not in row_of]
    if missing:
        raise SequenceError(f"{path}: field 'frame_id': no pose for frame '{missing[0]}'")
    rows = np.array([row_of[f] for f in frame_ids], np.int64)
    poses = np.tile(np.eye(4), (len(frame_ids), 1, 1))
    for i, name in enumerate(LIDAR_POSE_COLUMNS):
        values = table.column(name).to_numpy(zero_copy_only=False).astype(np.float64)[rows]
        bad = np.flatnonzero(~np.isfinite(values))
        if len(bad):
            raise SequenceError(
                f"{path}: column '{name}' is NaN/inf for frame '{frame_ids[bad[0]]}'"
            )
        poses[:, i // 4, i % 4] = values
    rotation = poses[:, :3, :3]
    error = np.abs(rotation @ rotation.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((error > 1e-3) | (np.linalg.det(rotation) < 0))
    if len(bad):
        raise SequenceError(
            f"{path}: columns 'lidar_pose_00'..'lidar_pose_22' of frame '{frame_ids[bad[0]]}' "
            "are not a rotation"
        )
    return poses
