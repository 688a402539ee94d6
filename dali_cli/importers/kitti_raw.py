"""KITTI raw data: a synced drive's velodyne scans, the day's calib files, and its tracklets
turned into per-frame boxes in the LiDAR frame with KITTI's label columns.

A drive directory `YYYY_MM_DD_drive_NNNN_sync` holds `velodyne_points/data/<index>.bin`
(float32 x, y, z, reflectance, 10-digit frame index) and, when labelled, `tracklet_labels.xml`;
its parent (the date folder) holds `calib_cam_to_cam.txt` (R_rect_00, P_rect_02, S_rect_02) and
`calib_velo_to_cam.txt` (R, T). With poses, `oxts/data/<index>.txt` (one GPS/IMU record a scan)
and the date folder's `calib_imu_to_velo.txt` give each scan's LiDAR pose (dali_cli.importers.oxts),
kept as the frame set's sequence table (dali_cli.store.sequence).

Tracklets (the raw devkit's `cpp/tracklets.h`, `matlab/run_demoTracklets.m`) are in the Velodyne
frame: a box of size h, w, l per object, and per frame from `first_frame` on a pose tx, ty, tz
(the centre of the box's bottom face), rz (rotation about z of the object's x axis, which runs
along its length), a truncation state (-1 unset, 0 in the image, 1 truncated, 2 out of the
image, 99 behind it) and an occlusion state (-1 unset, 0 visible, 1 partly, 2 fully). A dali box
is then (tx, ty, tz + h/2, l, w, h, rz). KITTI's label columns come from the box projected with
the drive's P_rect_02 and R_rect_00 (`dali_cli.importers.camera.kitti_label_columns`): the
clipped 2D box, alpha and the truncated share of the 2D box; a pose marked out of or behind the
image gets truncation 1 (KITTI's evaluation then ignores it at every difficulty), and the
occlusion state is KITTI's occluded level (unset -> 3, unknown).
"""

from __future__ import annotations

import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dali_cli.columns import Columns
from dali_cli.geometry import count_points_in_boxes, wrap_angle
from dali_cli.importers.beams import BeamThinning
from dali_cli.importers.camera import kitti_label_columns
from dali_cli.importers.common import (
    ImportFormatError,
    indexed_scan_ids,
    keyed_matrix,
    read_keyed,
    write_imported,
)
from dali_cli.importers.kitti import (
    DEFAULT_IMAGE_SIZE,
    Calibration,
    camera_fov_mask,
    read_velodyne,
)
from dali_cli.labels import plausibility
from dali_cli.store.artifacts import BoxTable
from dali_cli.store.manifest import BuildResult
from dali_cli.store.sequence import SEQUENCE_TABLE, write_sequence

TRACKLET_FILE = "tracklet_labels.xml"
MAX_TRACKLET_BYTES = 256 * 1024 * 1024  # the largest raw drive's tracklets are ~30 MB
TRUNCATION_OUT_OF_IMAGE = (2, 99)  # OUT_IMAGE, BEHIND_IMAGE
OCCLUSION_UNKNOWN = 3  # KITTI label_2's "unknown" occlusion level
_POSE_FIELDS = ("tx", "ty", "tz", "rz", "occlusion", "truncation")


# ---------------------------------------------------------------------------------------------
# Calibration


def read_raw_calib(calib_dir: str | Path) -> tuple[Calibration, tuple[int, int]]:
    """The day's calibration of camera 2 from `calib_cam_to_cam.txt` and `calib_velo_to_cam.txt`.

    Returns the Calibration (P2 = P_rect_02, R0_rect = R_rect_00, Tr_velo_to_cam = [R | T]) and
    the rectified image size (width, height) from S_rect_02 (KITTI's 1242 x 375 when absent).
    """
    calib_dir = Path(calib_dir)
    cam_path, velo_path = calib_dir / "calib_cam_to_cam.txt", calib_dir / "calib_velo_to_cam.txt"
    cam, velo = read_keyed(cam_path), read_keyed(velo_path)
    p2 = keyed_matrix(cam_path, cam, "P_rect_02", (3, 4))
    r0 = keyed_matrix(cam_path, cam, "R_rect_00", (3, 3))
    rotation = keyed_matrix(velo_path, velo, "R", (3, 3))
    translation = keyed_matrix(velo_path, velo, "T", (3, 1))
    if abs(np.linalg.det(r0)) < 1e-6 or abs(np.linalg.det(rotation)) < 1e-6:
        raise ImportFormatError(f"{calib_dir}: R_rect_00 or the velodyne R is singular")
    size = DEFAULT_IMAGE_SIZE
    if "S_rect_02" in cam:
        width, height = keyed_matrix(cam_path, cam, "S_rect_02", (1, 2))[0]
        if width < 1 or height < 1:
            raise ImportFormatError(f"{cam_path}, line {cam['S_rect_02'][0]}: 'S_rect_02' <= 0")
        size = (int(round(width)), int(round(height)))
    calib = Calibration(P2=p2, R0_rect=r0, Tr_velo_to_cam=np.c_[rotation, translation])
    return calib, size


def read_imu_to_velo(path: str | Path) -> np.ndarray:
    """`(4, 4)` x_velo = M x_imu from a raw `calib_imu_to_velo.txt` (R: 9 values, T: 3)."""
    path = Path(path)
    values = read_keyed(path)
    rotation = keyed_matrix(path, values, "R", (3, 3))
    translation = keyed_matrix(path, values, "T", (3, 1))
    if abs(np.linalg.det(rotation)) < 1e-6:
        raise ImportFormatError(f"{path}, line {values['R'][0]}: 'R' is singular")
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rotation, translation[:, 0]
    return matrix


# ---------------------------------------------------------------------------------------------
# Tracklets


@dataclass
class TrackletPoses(Columns):
    """Every pose of a tracklet file, one row per (object, frame) (N rows).

    frame : (N,) int64 frame index; label : (N,) object str (objectType); hwl : (N, 3) float64
    metres; pose : (N, 4) float64 tx, ty, tz (bottom centre, Velodyne frame, metres), rz (rad);
    occlusion : (N,) int32 state; truncation : (N,) int32 state; track : (N,) int32 tracklet index.
    """

    frame: np.ndarray
    label: np.ndarray
    hwl: np.ndarray
    pose: np.ndarray
    occlusion: np.ndarray
    truncation: np.ndarray
    track: np.ndarray

    def boxes(self) -> np.ndarray:
        """`(N, 7)` float64 dali boxes: x, y, z (geometric centre), l, w, h, yaw."""
        h, w, l = self.hwl[:, 0], self.hwl[:, 1], self.hwl[:, 2]  # noqa: E741
        x, y, z, rz = self.pose.T
        return np.c_[x, y, z + h / 2, l, w, h, wrap_angle(rz)]

    def select(self, mask: np.ndarray) -> TrackletPoses:
        return TrackletPoses(*(getattr(self, name)[mask] for name in self.__dataclass_fields__))


def _text(element, tag: str, path: Path, where: str) -> str:
    child = element.find(tag)
    if child is None or child.text is None or not child.text.strip():
        raise ImportFormatError(f"{path}: {where}: field '{tag}' missing or empty")
    return child.text.strip()


def _number(element, tag: str, path: Path, where: str, kind=float):
    text = _text(element, tag, path, where)
    try:
        value = kind(text)
    except ValueError:
        raise ImportFormatError(
            f"{path}: {where}: field '{tag}' is not a number ({text!r})"
        ) from None
    if kind is float and not np.isfinite(value):
        raise ImportFormatError(f"{path}: {where}: field '{tag}' is NaN/inf")
    return value


def _parse_xml(path: Path):
    try:
        size = path.stat().st_size
    except OSError as error:
        raise ImportFormatError(f"{path}: cannot read tracklet file ({error.strerror})") from None
    if size > MAX_TRACKLET_BYTES:
        raise ImportFormatError(
            f"{path}: tracklet file is {size} bytes, more than {MAX_TRACKLET_BYTES}"
        )
    from dali_cli.store.regular_files import UnreadableFileError, read_file_bytes

    try:
        raw = read_file_bytes(path, "tracklet file", "xml")
    except UnreadableFileError as error:
        raise ImportFormatError(str(error)) from None
    if b"<!ENTITY" in raw:
        raise ImportFormatError(f"{path}: tracklet file declares XML entities (refused)")
    try:
        return ElementTree.fromstring(raw)
    except ElementTree.ParseError as error:
        raise ImportFormatError(f"{path}: malformed XML ({error})") from None


def read_tracklets(path: str | Path) -> TrackletPoses:
    """Parse a KITTI raw `tracklet_labels.xml` into one row per annotated pose.

    Errors (ImportFormatError) name the file, the tracklet (0-based), the pose and the field.
    """
    path = Path(path)
    root = _parse_xml(path)
    tracklets = root.find("tracklets") if root.tag != "tracklets" else root
    if tracklets is None:
        raise ImportFormatError(f"{path}: no <tracklets> element")
    items = tracklets.findall("item")
    declared = tracklets.find("count")
    if declared is not None and declared.text and declared.text.strip() != str(len(items)):
        raise ImportFormatError(
            f"{path}: <count> says {declared.text.strip()} tracklets, the file has {len(items)}"
        )
    rows = {name: [] for name in ("frame", "label", "hwl", "pose", "occ", "trunc", "track")}
    for index, item in enumerate(items):
        where = f"tracklet {index}"
        label = _text(item, "objectType", path, where)
        hwl = [_number(item, tag, path, where) for tag in ("h", "w", "l")]
        if min(hwl) <= 0:
            raise ImportFormatError(f"{path}: {where}: size h, w, l must be > 0, got {hwl}")
        first = _number(item, "first_frame", path, where, int)
        if first < 0:
            raise ImportFormatError(f"{path}: {where}: field 'first_frame' is negative ({first})")
        poses = item.find("poses")
        if poses is None:
            raise ImportFormatError(f"{path}: {where}: field 'poses' missing")
        for offset, pose in enumerate(poses.findall("item")):
            at = f"{where}, pose {offset}"
            values = [_number(pose, tag, path, at) for tag in _POSE_FIELDS[:4]]
            states = [_number(pose, tag, path, at, int) for tag in _POSE_FIELDS[4:]]
            rows["frame"].append(first + offset)
            rows["label"].append(label)
            rows["hwl"].append(hwl)
            rows["pose"].append(values)
            rows["occ"].append(states[0])
            rows["trunc"].append(states[1])
            rows["track"].append(index)
    return TrackletPoses(
        frame=np.asarray(rows["frame"], np.int64),
        label=np.asarray(rows["label"], dtype=object),
        hwl=np.asarray(rows["hwl"], np.float64).reshape(-1, 3),
        pose=np.asarray(rows["pose"], np.float64).reshape(-1, 4),
        occlusion=np.asarray(rows["occ"], np.int32),
        truncation=np.asarray(rows["trunc"], np.int32),
        track=np.asarray(rows["track"], np.int32),
    )


def tracklet_table(
    frame_id: str,
    poses: TrackletPoses,
    points: np.ndarray,
    calib: Calibration,
    image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE,
) -> BoxTable:
    """One frame's poses (already selected) -> a BoxTable with KITTI's label columns and the
    in-box point counts of `points` `(n, 4)`."""
    boxes = poses.boxes()
    columns = kitti_label_columns(boxes, np.zeros(len(boxes)), calib, image_size)
    out_of_image = np.isin(poses.truncation, TRUNCATION_OUT_OF_IMAGE)
    columns["truncated"] = np.where(out_of_image, 1.0, columns["truncated"]).astype(np.float32)
    columns["occluded"] = np.where(
        poses.occlusion < 0, OCCLUSION_UNKNOWN, np.minimum(poses.occlusion, 2)
    ).astype(np.int32)
    counts = count_points_in_boxes(points, boxes) if len(boxes) else np.zeros(0, np.int32)
    return BoxTable.from_arrays(
        np.full(len(boxes), frame_id, dtype=object),
        boxes,
        score=np.ones(len(boxes), np.float32),
        label=poses.label,
        num_points=counts,
        **columns,
    )


# ---------------------------------------------------------------------------------------------
# The drive and the import stage


@dataclass(frozen=True)
class RawDrive:
    """Where a synced drive's files live."""

    velodyne_dir: Path
    calib_dir: Path
    tracklets: Path | None  # None: unlabelled

    @classmethod
    def of(
        cls,
        drive_dir: str | Path,
        calib_dir: str | Path | None = None,
        tracklets: str | Path | None = None,
        labels: bool = True,
    ) -> RawDrive:
        """DRIVE_DIR holds velodyne_points/data; the calib files default to DRIVE_DIR/..; the
        tracklets to DRIVE_DIR/tracklet_labels.xml when present (`labels=False`: none)."""
        drive_dir = Path(drive_dir)
        velodyne = drive_dir / "velodyne_points" / "data"
        if not velodyne.is_dir():
            raise ImportFormatError(f"{drive_dir}: no velodyne_points/data directory")
        calib = Path(calib_dir) if calib_dir is not None else drive_dir.resolve().parent
        for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt"):
            if not (calib / name).is_file():
                raise ImportFormatError(f"{calib / name}: calib file missing (see --calib-dir)")
        found = None
        if labels:
            found = Path(tracklets) if tracklets is not None else drive_dir / TRACKLET_FILE
            if not found.is_file():
                if tracklets is not None:
                    raise ImportFormatError(f"{found}: tracklet file not found")
                found = None
        return cls(velodyne_dir=velodyne, calib_dir=calib, tracklets=found)

    @property
    def oxts_dir(self) -> Path:
        return self.velodyne_dir.parent.parent / "oxts" / "data"

    @property
    def imu_to_velo_file(self) -> Path:
        return self.calib_dir / "calib_imu_to_velo.txt"

    def lidar_poses(self, frame_ids: list[str]) -> np.ndarray:
        """`(n, 4, 4)` LiDAR pose of each scan in the first scan's LiDAR frame, from the OXTS
        records; ImportFormatError naming the file (and field) that is missing or malformed."""
        from dali_cli.importers.oxts import drive_lidar_poses

        if not self.oxts_dir.is_dir():
            raise ImportFormatError(f"{self.oxts_dir}: no OXTS records (needed for the poses)")
        if not self.imu_to_velo_file.is_file():
            raise ImportFormatError(f"{self.imu_to_velo_file}: calib file missing (the poses)")
        return drive_lidar_poses(self.oxts_dir, read_imu_to_velo(self.imu_to_velo_file), frame_ids)

    def frame_ids(self) -> list[str]:
        """Every `velodyne_points/data/*.bin` stem (each a whole frame index), sorted."""
        return indexed_scan_ids(self.velodyne_dir, "frame index")


def build_import(
    out: str | Path,
    drive: RawDrive,
    frame_ids: list[str],
    crop_fov: bool = False,
    sensor: str = "kitti",
    progress: bool = True,
    poses: bool = False,
    thinning: BeamThinning = BeamThinning(),
) -> BuildResult:
    """Stage body of `dali import kitti-raw`: every scan, and its tracklet boxes when labelled
    (`progress`: a progress bar on stderr); `poses`: the scans' LiDAR poses from the drive's OXTS
    records as OUT/sequence.parquet; `thinning`: the beams each scan keeps, before the crop."""
    calib, image_size = read_raw_calib(drive.calib_dir)
    lidar_poses = drive.lidar_poses(frame_ids) if poses else None  # read first: fail early
    poses = read_tracklets(drive.tracklets) if drive.tracklets is not None else None
    notes = ["points: velodyne_points/data scans (LiDAR frame)", *thinning.notes()]
    if poses is not None:
        indices = np.array([int(frame_id) for frame_id in frame_ids], np.int64)
        outside = int((~np.isin(poses.frame, indices)).sum())
        notes += [
            "boxes: tracklet poses (bottom centre, rz) -> geometric centre; KITTI columns by "
            "projecting with P_rect_02 and R_rect_00",
            f"{outside} tracklet poses fall on frames outside the drive's scans and are dropped",
        ]

    def frames():
        for frame_id in frame_ids:
            points = thinning.apply(read_velodyne(drive.velodyne_dir / f"{frame_id}.bin"))
            if crop_fov:
                points = points[camera_fov_mask(points, calib, image_size)]
            table = None
            if poses is not None:
                table = tracklet_table(
                    frame_id, poses.select(poses.frame == int(frame_id)), points, calib, image_size
                )
                plausibility.refuse_implausible(
                    table.boxes, np.ones(len(table), bool), str(drive.tracklets), table.frame_id
                )
            yield frame_id, points, table

    attrs = {"source_format": "kitti-raw", "crop_fov": bool(crop_fov), **thinning.params()}
    result = write_imported(out, frames(), sensor, attrs, total=len(frame_ids), progress=progress)
    if lidar_poses is not None:
        write_sequence(out, frame_ids, lidar_poses)
        travelled = np.linalg.norm(np.diff(lidar_poses[:, :3, 3], axis=0), axis=1).sum()
        notes.append(
            f"{SEQUENCE_TABLE}: each scan's LiDAR pose from its OXTS record ({travelled:.1f} m driven)"
        )
    result.notes.extend(notes)
    return result
