"""KITTI odometry (and SemanticKITTI) sequences: velodyne scans, calib.txt, times.txt and poses.

A sequence directory `sequences/NN` holds `velodyne/<index>.bin` (float32 x, y, z, reflectance,
6-digit scan index) and, when the dataset ships them, `calib.txt` (`P0:` .. `P3:` the rectified
cameras' 3 x 4 projections, `Tr:` the 3 x 4 velodyne -> camera 0 transform; the cameras are
already rectified, so R0_rect is the identity) and `times.txt` (one timestamp in seconds a line).
The ground-truth poses (sequences 00-10) are 3 x 4 row-major matrices, one a line: camera 0 of
scan i in the coordinates of camera 0 of scan 0. They are in `sequences/NN/poses.txt`
(SemanticKITTI) or in the odometry devkit's `poses/NN.txt` beside `sequences/`.

Line i of times.txt and of the poses belongs to scan i (the file name's index), so a directory
holding only part of a sequence's scans reads the lines of the scans it has; a scan without its
line is an error naming the file. Both are kept with the frames as `sequence.parquet`
(dali_cli.store.sequence): time_s, camera_pose_RC as given and, with calib.txt, each scan's
LiDAR pose inv(Tr) @ P_i @ Tr in the LiDAR frame of scan 0 of the sequence (scan 0 even when
the directory holds a later part of it).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from dali_cli.importers.beams import BeamThinning
from dali_cli.importers.common import (
    ImportFormatError,
    indexed_scan_ids,
    keyed_matrix,
    read_keyed,
    read_text_lines,
    write_imported,
)
from dali_cli.importers.kitti import (
    DEFAULT_IMAGE_SIZE,
    Calibration,
    camera_fov_mask,
    png_size,
    read_velodyne,
)
from dali_cli.store.manifest import BuildResult
from dali_cli.store.sequence import SEQUENCE_TABLE, lidar_from_camera_poses, sequence_table

# ---------------------------------------------------------------------------------------------
# Calibration, timestamps and poses


def read_odometry_calib(path: str | Path) -> Calibration:
    """camera 2's Calibration from an odometry `calib.txt`: P2, R0_rect = I, Tr_velo_to_cam = Tr.

    Errors (ImportFormatError) name the file, the line and the key."""
    path = Path(path)
    values = read_keyed(path)
    p2 = keyed_matrix(path, values, "P2", (3, 4))
    tr = keyed_matrix(path, values, "Tr", (3, 4))
    if abs(np.linalg.det(tr[:, :3])) < 1e-6:
        raise ImportFormatError(f"{path}, line {values['Tr'][0]}: 'Tr' rotation is singular")
    return Calibration(P2=p2, R0_rect=np.eye(3), Tr_velo_to_cam=tr)


def read_rows(path: str | Path, what: str, width: int) -> np.ndarray:
    """`(n, width)` float64 of a whitespace-separated text file, one row a line (blank lines
    refused: they would shift every later scan's row). Errors name the file, line and field."""
    path = Path(path)
    rows = []
    for number, line in enumerate(read_text_lines(path, what), start=1):
        fields = line.split()
        if len(fields) != width:
            raise ImportFormatError(
                f"{path}, line {number}: {what} has {len(fields)} values, expected {width}"
            )
        try:
            row = [float(field) for field in fields]
        except ValueError:
            raise ImportFormatError(
                f"{path}, line {number}: {what} has a non-numeric value"
            ) from None
        if not np.isfinite(row).all():
            raise ImportFormatError(f"{path}, line {number}: {what} has NaN/inf values")
        rows.append(row)
    return np.asarray(rows, np.float64).reshape(-1, width)


def rows_of_scans(rows: np.ndarray, path: Path, what: str, indices: np.ndarray) -> np.ndarray:
    """The rows of the scans `indices` (line i belongs to scan i); an error naming the file when
    it has fewer lines than the highest scan index needs."""
    needed = int(indices.max()) + 1
    if len(rows) < needed:
        raise ImportFormatError(
            f"{path}: {len(rows)} {what} lines for scans up to {needed - 1:06d} (one line per "
            f"scan, line i for scan i: {needed} needed)"
        )
    return rows[indices]


# ---------------------------------------------------------------------------------------------
# The sequence and the import stage


@dataclass(frozen=True)
class OdometrySequence:
    """Where a sequence's files live; calib, times and poses are None when absent."""

    velodyne_dir: Path
    calib: Path | None
    times: Path | None
    poses: Path | None

    @classmethod
    def of(
        cls,
        sequence_dir: str | Path,
        calib: str | Path | None = None,
        poses: str | Path | None = None,
    ) -> OdometrySequence:
        """SEQUENCE_DIR holds velodyne/; calib defaults to SEQUENCE_DIR/calib.txt, the poses to
        SEQUENCE_DIR/poses.txt, else SEQUENCE_DIR/../../poses/<name>.txt (the devkit layout)."""
        sequence_dir = Path(sequence_dir)
        velodyne = sequence_dir / "velodyne"
        if not velodyne.is_dir():
            raise ImportFormatError(f"{sequence_dir}: no velodyne directory")
        calib_path = Path(calib) if calib is not None else sequence_dir / "calib.txt"
        if calib is not None and not calib_path.is_file():
            raise ImportFormatError(f"{calib_path}: calib file not found")
        times = sequence_dir / "times.txt"
        if poses is not None:
            poses_path = Path(poses)
            if not poses_path.is_file():
                raise ImportFormatError(f"{poses_path}: poses file not found")
        else:
            name = sequence_dir.resolve().name
            candidates = (
                sequence_dir / "poses.txt",
                sequence_dir / ".." / ".." / "poses" / f"{name}.txt",
            )
            poses_path = next((path for path in candidates if path.is_file()), None)
        return cls(
            velodyne_dir=velodyne,
            calib=calib_path if calib_path.is_file() else None,
            times=times if times.is_file() else None,
            poses=poses_path,
        )

    def frame_ids(self) -> list[str]:
        """Every `velodyne/*.bin` stem (each a whole scan index), sorted."""
        return indexed_scan_ids(self.velodyne_dir)

    def image_size(self) -> tuple[int, int]:
        """camera 2's image size from `image_2/000000.png` when present, else KITTI's default."""
        return png_size(self.velodyne_dir.parent / "image_2" / "000000.png") or DEFAULT_IMAGE_SIZE

    def sequence_table(
        self, frame_ids: list[str], velo_to_cam: np.ndarray | None = None
    ) -> pa.Table | None:
        """The sequence table (dali_cli.store.sequence) of the scans: frame_id, index, time_s
        (times.txt), camera_pose_RC (the poses as given) and, with `velo_to_cam` (calib.txt's
        Tr, 3 x 4), lidar_pose_RC; None when the sequence has neither times nor poses. Reads
        and checks both files."""
        if self.times is None and self.poses is None:
            return None
        indices = np.array([int(frame_id) for frame_id in frame_ids], np.int64)
        time_s = camera = lidar = None
        if self.times is not None:
            times = read_rows(self.times, "times.txt timestamp", 1)
            time_s = rows_of_scans(times, self.times, "timestamp", indices)[:, 0]
        if self.poses is not None:
            rows = rows_of_scans(read_rows(self.poses, "pose", 12), self.poses, "pose", indices)
            camera = rows.reshape(-1, 3, 4)
            if velo_to_cam is not None:
                lidar = lidar_from_camera_poses(camera, velo_to_cam)
        return sequence_table(
            frame_ids, index=indices, time_s=time_s, camera_poses=camera, lidar_poses=lidar
        )


def front_mask(points: np.ndarray, front_deg: float) -> np.ndarray:
    """`(N,)` bool: points within ±front_deg / 2 of straight ahead (+x) in azimuth."""
    azimuth = np.degrees(np.abs(np.arctan2(points[:, 1], points[:, 0])))
    return azimuth <= front_deg / 2


def build_import(
    out: str | Path,
    sequence: OdometrySequence,
    frame_ids: list[str],
    calib: Calibration | None,
    table: pa.Table | None,
    crop_fov: bool = False,
    crop_front_deg: float | None = None,
    sensor: str = "kitti",
    progress: bool = True,
    thinning: BeamThinning = BeamThinning(),
) -> BuildResult:
    """Stage body of `dali import kitti-odometry`: every scan (unlabeled; cropped to camera 2's
    image through `calib` with `crop_fov`, to the front `crop_front_deg` degrees of azimuth), and
    `table` (`OdometrySequence.sequence_table`) as OUT/sequence.parquet (`progress`: a progress
    bar on stderr; `thinning`: the beams each scan keeps, before the crops)."""
    from dali_cli.store.sequence import write_table

    image_size = sequence.image_size()
    notes = ["points: velodyne scans (LiDAR frame), no labels", *thinning.notes()]
    if crop_fov:
        notes.append(
            f"cropped to camera 2's image ({image_size[0]} x {image_size[1]}) by P2 and Tr"
        )
    if crop_front_deg is not None:
        notes.append(f"cropped to the front {crop_front_deg:g} degrees of azimuth")

    def frames():
        for frame_id in frame_ids:
            points = thinning.apply(read_velodyne(sequence.velodyne_dir / f"{frame_id}.bin"))
            if crop_fov:
                points = points[camera_fov_mask(points, calib, image_size)]
            if crop_front_deg is not None:
                points = points[front_mask(points, crop_front_deg)]
            yield frame_id, points, None

    attrs = {
        "source_format": "kitti-odometry",
        "crop_fov": bool(crop_fov),
        "crop_front_deg": crop_front_deg,
        **thinning.params(),
    }
    result = write_imported(out, frames(), sensor, attrs, total=len(frame_ids), progress=progress)
    if table is not None:
        write_table(out, table)
        kept = [
            name for name, path in (("times", sequence.times), ("poses", sequence.poses)) if path
        ]
        notes.append(f"{SEQUENCE_TABLE}: the {' and '.join(kept)} of every scan (line i: scan i)")
        if sequence.poses is not None:
            notes.append(
                f"{SEQUENCE_TABLE}: LiDAR poses inv(Tr) @ P_i @ Tr in scan 0's LiDAR frame"
                if "lidar_pose_00" in table.column_names
                else f"{SEQUENCE_TABLE}: camera poses only (no calib.txt: no LiDAR poses)"
            )
    result.notes.extend(notes)
    return result
