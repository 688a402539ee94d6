"""KITTI object data: velodyne scans, calib files, and label_2 boxes converted to the LiDAR frame.

Camera-frame labels (rectified camera: x right, y down, z forward; `h w l`, bottom-centre location,
rotation_y about camera y) become dali boxes (LiDAR frame, geometric centre, yaw CCW from +x)
through the frame's calib: centre_rect = location - (0, h/2, 0), centre_lidar =
(R0_rect · Tr_velo_to_cam)^-1 · centre_rect. The heading is carried as a direction vector through
the same rotation rather than by the usual yaw = -rotation_y - pi/2, which assumes the velodyne and
rectified camera axes are exactly aligned (on KITTI the two agree to about 1e-4 rad; the vector
form stays right for any calib). `lidar_boxes_to_camera` is the inverse, up to the heading's
component along the camera tilt (about 1e-4 rad on KITTI).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dali_cli.columns import Columns
from dali_cli.geometry import count_points_in_boxes, wrap_angle
from dali_cli.importers import kitti_label
from dali_cli.importers.beams import BeamThinning
from dali_cli.importers.common import (
    ImportFormatError,
    check_id,
    read_float_records,
    read_text_lines,
    write_imported,
)
from dali_cli.labels import plausibility
from dali_cli.store.artifacts import BoxTable
from dali_cli.store.manifest import BuildResult

DEFAULT_IMAGE_SIZE = (1242, 375)  # width, height in pixels; KITTI images are 1224..1242 x 370..376
IGNORE_TYPES = ("DontCare",)  # rows without a 3D box: kept for their 2D region only


# ---------------------------------------------------------------------------------------------
# Point clouds


def read_velodyne(path: str | Path, intensity_max: float = 1.0) -> np.ndarray:
    """A velodyne `.bin` scan: `(n, 4)` float32 x, y, z, reflectance in the LiDAR frame (metres),
    the reflectance divided by `intensity_max`, held to the frame-set contract
    (common.check_scan_contract)."""
    from dali_cli.importers.common import check_scan_contract

    return check_scan_contract(read_float_records(path, 4), path, intensity_max)


# ---------------------------------------------------------------------------------------------
# Calibration


@dataclass(frozen=True)
class Calibration:
    """One frame's KITTI calibration.

    P2 : (3, 4) float64, left colour camera projection (rectified camera -> pixels)
    R0_rect : (3, 3) float64, rectifying rotation
    Tr_velo_to_cam : (3, 4) float64, velodyne -> (unrectified) camera 0
    """

    P2: np.ndarray
    R0_rect: np.ndarray
    Tr_velo_to_cam: np.ndarray

    @property
    def velo_to_rect(self) -> np.ndarray:
        """`(4, 4)` homogeneous LiDAR -> rectified camera transform, R0_rect · Tr_velo_to_cam."""
        r0 = np.eye(4)
        r0[:3, :3] = self.R0_rect
        tr = np.eye(4)
        tr[:3, :] = self.Tr_velo_to_cam
        return r0 @ tr

    @property
    def rect_to_velo(self) -> np.ndarray:
        """`(4, 4)` inverse of `velo_to_rect`."""
        return np.linalg.inv(self.velo_to_rect)

    def lidar_to_rect(self, xyz: np.ndarray) -> np.ndarray:
        """`(N, 3)` LiDAR points -> `(N, 3)` float64 rectified-camera points."""
        transform = self.velo_to_rect
        return np.asarray(xyz, np.float64)[:, :3] @ transform[:3, :3].T + transform[:3, 3]

    def rect_to_lidar(self, xyz: np.ndarray) -> np.ndarray:
        """`(N, 3)` rectified-camera points -> `(N, 3)` float64 LiDAR points."""
        transform = self.rect_to_velo
        return np.asarray(xyz, np.float64)[:, :3] @ transform[:3, :3].T + transform[:3, 3]

    def rect_to_image(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project `(N, 3)` rectified-camera points with P2: `(N, 2)` pixels (u, v), `(N,)` depth.

        Points at depth <= 0 get meaningless pixels; callers check the depth.
        """
        xyz = np.asarray(xyz, np.float64)
        homogeneous = xyz @ self.P2[:, :3].T + self.P2[:, 3]  # (N, 3)
        depth = homogeneous[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            pixels = homogeneous[:, :2] / depth[:, None]
        return pixels, xyz[:, 2]


_CALIB_KEYS = {
    "P2": ("P2",),
    "R0_rect": ("R0_rect", "R_rect", "R0"),
    "Tr_velo_to_cam": ("Tr_velo_to_cam", "Tr_velo_cam"),
}
_CALIB_SHAPES = {"P2": (3, 4), "R0_rect": (3, 3), "Tr_velo_to_cam": (3, 4)}


def read_calib(path: str | Path) -> Calibration:
    """Parse a KITTI object calib file (`KEY: v1 v2 ...` lines). Errors name file, line and key."""
    path = Path(path)
    lines = read_text_lines(path, "calib file")
    values: dict[str, tuple[int, np.ndarray]] = {}
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:
            raise ImportFormatError(f"{path}, line {number}: expected 'KEY: values', got {line!r}")
        try:
            numbers = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError:
            raise ImportFormatError(
                f"{path}, line {number}: '{key.strip()}' has a non-numeric value"
            ) from None
        values[key.strip()] = (number, numbers)
    matrices = {}
    for name, aliases in _CALIB_KEYS.items():
        found = next((alias for alias in aliases if alias in values), None)
        if found is None:
            raise ImportFormatError(f"{path}: calib key '{name}' missing")
        number, numbers = values[found]
        shape = _CALIB_SHAPES[name]
        if numbers.size != shape[0] * shape[1]:
            raise ImportFormatError(
                f"{path}, line {number}: '{found}' has {numbers.size} values, expected {shape[0] * shape[1]}"
            )
        if not np.isfinite(numbers).all():
            raise ImportFormatError(f"{path}, line {number}: '{found}' has NaN/inf values")
        matrices[name] = numbers.reshape(shape)
    if (
        abs(np.linalg.det(matrices["R0_rect"])) < 1e-6
        or abs(np.linalg.det(matrices["Tr_velo_to_cam"][:, :3])) < 1e-6
    ):
        raise ImportFormatError(f"{path}: R0_rect or Tr_velo_to_cam is singular")
    return Calibration(**matrices)


def png_size(path: str | Path) -> tuple[int, int] | None:
    """(width, height) from a PNG header, or None when the file is absent or not a PNG."""
    try:
        with open(path, "rb") as handle:
            header = handle.read(24)
    except OSError:
        return None
    if len(header) < 24 or header[:8] != b"\x89PNG\r\n\x1a\n":
        return None
    width, height = struct.unpack(">II", header[16:24])
    return int(width), int(height)


# ---------------------------------------------------------------------------------------------
# Labels (camera frame) <-> boxes (LiDAR frame)


@dataclass
class CameraObjects(Columns):
    """Raw label_2 rows of one file, camera frame, as arrays (N objects).

    type : (N,) object str; truncated (N,) float32; occluded (N,) int32; alpha (N,) float64;
    bbox : (N, 4) float32 left, top, right, bottom (pixels); hwl : (N, 3) float64 metres;
    location : (N, 3) float64 bottom centre in the rectified camera frame; rotation_y : (N,) float64;
    score : (N,) float32 (1 when the file has 15 fields).
    """

    type: np.ndarray
    truncated: np.ndarray
    occluded: np.ndarray
    alpha: np.ndarray
    bbox: np.ndarray
    hwl: np.ndarray
    location: np.ndarray
    rotation_y: np.ndarray
    score: np.ndarray


def parse_label_file(path: str | Path) -> CameraObjects:
    """Read one label_2 file (15 fields per line, or 16 with a detection score) as raw camera
    fields. Parsing is `dali_cli.importers.kitti_label`'s: malformed lines raise ArtifactError naming the
    file and line (`path:line: ...`); DontCare's placeholder size -1 becomes 0."""
    table = kitti_label.read_label_file(path)
    hwl, location, rotation_y = kitti_label.pseudo_lidar_to_camera(table.boxes)
    return CameraObjects(
        type=np.asarray(table["label"], dtype=object),
        truncated=np.asarray(table["truncated"], np.float32),
        occluded=np.asarray(table["occluded"], np.int32),
        alpha=np.asarray(table["alpha"], np.float64),
        bbox=np.stack([table[name] for name in kitti_label.BBOX_COLUMNS], axis=1).astype(
            np.float32
        ),
        hwl=hwl,
        location=location,
        rotation_y=rotation_y,
        score=np.asarray(table["score"], np.float32),
    )


def camera_boxes_to_lidar(
    location: np.ndarray, hwl: np.ndarray, rotation_y: np.ndarray, calib: Calibration
) -> np.ndarray:
    """KITTI camera boxes -> `(N, 7)` float64 LiDAR boxes (x, y, z, l, w, h, yaw).

    location : (N, 3) bottom centre (rectified camera, metres); hwl : (N, 3); rotation_y : (N,).
    """
    location = np.asarray(location, np.float64).reshape(-1, 3)
    hwl = np.asarray(hwl, np.float64).reshape(-1, 3)
    rotation_y = np.asarray(rotation_y, np.float64).reshape(-1)
    centre_rect = location - np.c_[np.zeros(len(hwl)), hwl[:, 0] / 2, np.zeros(len(hwl))]
    centre = calib.rect_to_lidar(centre_rect)  # (N, 3)
    heading_rect = np.c_[
        np.cos(rotation_y), np.zeros_like(rotation_y), -np.sin(rotation_y)
    ]  # (N, 3)
    heading = heading_rect @ calib.rect_to_velo[:3, :3].T  # (N, 3)
    yaw = wrap_angle(np.arctan2(heading[:, 1], heading[:, 0]))
    return np.c_[centre, hwl[:, 2], hwl[:, 1], hwl[:, 0], yaw]


def lidar_boxes_to_camera(
    boxes: np.ndarray, calib: Calibration
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`(N, 7)` LiDAR boxes -> KITTI camera boxes: location (N, 3) bottom centre, hwl (N, 3),
    rotation_y (N,) in [-pi, pi). Inverse of `camera_boxes_to_lidar`."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    centre_rect = calib.lidar_to_rect(boxes[:, :3])
    hwl = boxes[:, [5, 4, 3]].copy()
    location = centre_rect + np.c_[np.zeros(len(boxes)), hwl[:, 0] / 2, np.zeros(len(boxes))]
    yaw = boxes[:, 6]
    heading = np.c_[np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)] @ calib.velo_to_rect[:3, :3].T
    rotation_y = wrap_angle(np.arctan2(-heading[:, 2], heading[:, 0]))
    return location, hwl, rotation_y


def observation_angle(location: np.ndarray, rotation_y: np.ndarray) -> np.ndarray:
    """KITTI alpha: rotation_y minus the viewing ray's angle, atan2(x, z), in [-pi, pi). `(N,)`."""
    location = np.asarray(location, np.float64).reshape(-1, 3)
    return wrap_angle(np.asarray(rotation_y) - np.arctan2(location[:, 0], location[:, 2]))


def camera_box_corners(location: np.ndarray, hwl: np.ndarray, rotation_y: np.ndarray) -> np.ndarray:
    """`(N, 8, 3)` corners of KITTI camera boxes in the rectified camera frame (devkit order:
    bottom face then top face)."""
    location = np.asarray(location, np.float64).reshape(-1, 3)
    h, w, l = (np.asarray(hwl, np.float64).reshape(-1, 3)[:, i] for i in range(3))  # noqa: E741
    x = np.stack([l, l, -l, -l, l, l, -l, -l], axis=1) / 2  # (N, 8) along the heading
    y = np.stack([np.zeros_like(h)] * 4 + [-h] * 4, axis=1)  # (N, 8) camera y points down
    z = np.stack([w, -w, -w, w, w, -w, -w, w], axis=1) / 2  # (N, 8)
    cos, sin = np.cos(rotation_y)[:, None], np.sin(rotation_y)[:, None]
    corners = np.stack([cos * x + sin * z, y, -sin * x + cos * z], axis=2)  # (N, 8, 3)
    return corners + location[:, None, :]


def image_boxes(
    location: np.ndarray,
    hwl: np.ndarray,
    rotation_y: np.ndarray,
    calib: Calibration,
    image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE,
    near_m: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """2D boxes from the projected 3D corners, clipped to the image.

    Returns `(N, 4)` float32 left, top, right, bottom (pixels) and `(N,)` bool visible: the box is
    in front of the camera and its clipped 2D box has a positive area. Corners closer than
    `near_m` are pushed to that depth before projecting, so a box that straddles the image plane
    projects towards the image border instead of flipping.
    """
    corners = camera_box_corners(location, hwl, rotation_y)  # (N, 8, 3)
    count = len(corners)
    depth_ok = corners[:, :, 2].max(axis=1) > near_m if count else np.zeros(0, bool)
    corners = corners.copy()
    corners[:, :, 2] = np.maximum(corners[:, :, 2], near_m)
    pixels, _ = calib.rect_to_image(corners.reshape(-1, 3))
    pixels = pixels.reshape(count, 8, 2)
    width, height = image_size
    left = np.clip(pixels[:, :, 0].min(axis=1), 0, width - 1)
    right = np.clip(pixels[:, :, 0].max(axis=1), 0, width - 1)
    top = np.clip(pixels[:, :, 1].min(axis=1), 0, height - 1)
    bottom = np.clip(pixels[:, :, 1].max(axis=1), 0, height - 1)
    visible = depth_ok & (right > left) & (bottom > top)
    return np.stack([left, top, right, bottom], axis=1).astype(np.float32), visible


def camera_fov_mask(
    points: np.ndarray, calib: Calibration, image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE
) -> np.ndarray:
    """`(N,)` bool: LiDAR points in front of the camera that project inside the image."""
    rect = calib.lidar_to_rect(points[:, :3])
    pixels, depth = calib.rect_to_image(rect)
    width, height = image_size
    with np.errstate(invalid="ignore"):
        return (
            (depth > 0)
            & (pixels[:, 0] >= 0)
            & (pixels[:, 0] < width)
            & (pixels[:, 1] >= 0)
            & (pixels[:, 1] < height)
        )


# ---------------------------------------------------------------------------------------------
# Frames and the import stage


@dataclass(frozen=True)
class KittiLayout:
    """Where one split's files live. label_dir may not exist (testing split, unlabelled target)."""

    velodyne_dir: Path
    label_dir: Path
    calib_dir: Path
    image_dir: Path

    @classmethod
    def of(
        cls, root: str | Path, split: str = "training", label_dir: str | Path | None = None
    ) -> KittiLayout:
        """ROOT may be the dataset root (holding `training/`, `testing/`) or a split directory."""
        root = Path(root)
        base = root / split if (root / split / "velodyne").is_dir() else root
        if not (base / "velodyne").is_dir():
            raise ImportFormatError(
                f"{root}: no velodyne directory (looked for {root / split / 'velodyne'} and {root / 'velodyne'})"
            )
        return cls(
            velodyne_dir=base / "velodyne",
            label_dir=Path(label_dir) if label_dir is not None else base / "label_2",
            calib_dir=base / "calib",
            image_dir=base / "image_2",
        )

    def frame_ids(self, ids: list[str] | None = None) -> list[str]:
        """The given ids (each must have a scan), else every `velodyne/*.bin` stem, sorted."""
        if ids is None:
            ids = sorted(
                check_id(path.stem, f"{path}: file name")
                for path in self.velodyne_dir.glob("*.bin")
            )
            if not ids:
                raise ImportFormatError(f"{self.velodyne_dir}: no .bin scans")
            return ids
        for position, frame_id in enumerate(ids):
            check_id(frame_id, f"frame id list, entry {position}")
        missing = [
            frame_id for frame_id in ids if not (self.velodyne_dir / f"{frame_id}.bin").is_file()
        ]
        if missing:
            raise ImportFormatError(
                f"{self.velodyne_dir}: no scan for frame '{missing[0]}' ({len(missing)} ids without a scan)"
            )
        return list(ids)

    def image_size(self, frame_id: str) -> tuple[int, int]:
        """The frame's image_2 PNG size when present, else the KITTI default 1242 x 375."""
        return png_size(self.image_dir / f"{frame_id}.png") or DEFAULT_IMAGE_SIZE


def objects_to_lidar_columns(objects: CameraObjects, calib: Calibration) -> tuple[np.ndarray, dict]:
    """Camera objects -> `(N, 7)` LiDAR boxes and the KITTI extra columns of docs/INTERFACES.md.

    DontCare rows have no 3D box: they get a zero box at the origin (zero size, so no point is ever
    inside) and keep their 2D region.
    """
    boxes = camera_boxes_to_lidar(objects.location, objects.hwl, objects.rotation_y, calib)
    ignore = np.isin(objects.type.astype(str), IGNORE_TYPES)
    boxes[ignore] = 0.0
    columns = {
        "truncated": objects.truncated,
        "occluded": objects.occluded,
        "alpha": objects.alpha,
        "bbox_left": objects.bbox[:, 0],
        "bbox_top": objects.bbox[:, 1],
        "bbox_right": objects.bbox[:, 2],
        "bbox_bottom": objects.bbox[:, 3],
    }
    return boxes, columns


def load_frame(
    layout: KittiLayout,
    frame_id: str,
    crop_fov: bool = False,
    intensity_max: float = 1.0,
    thinning: BeamThinning | None = None,
):
    """One frame: points `(n, 4)` float32 and its BoxTable, or None when it has no label file
    (`thinning`: the beams kept, before the crop; the in-box counts are of the kept points).

    The calib file is required when the frame has labels or `crop_fov` is set.
    """
    points = read_velodyne(layout.velodyne_dir / f"{frame_id}.bin", intensity_max)
    if thinning is not None:
        points = thinning.apply(points)
    label_path = layout.label_dir / f"{frame_id}.txt"
    has_labels = label_path.is_file()
    if not has_labels and (label_path.exists() or label_path.is_symlink()):
        raise ImportFormatError(f"{label_path}: not a label file (a directory or a broken link)")
    calib = None
    if has_labels or crop_fov:
        calib_path = layout.calib_dir / f"{frame_id}.txt"
        if not calib_path.is_file():
            raise ImportFormatError(f"{calib_path}: calib file missing for frame '{frame_id}'")
        calib = read_calib(calib_path)
    if crop_fov:
        points = points[camera_fov_mask(points, calib, layout.image_size(frame_id))]
    if not has_labels:
        return points, None
    objects = parse_label_file(label_path)
    boxes, extra = objects_to_lidar_columns(objects, calib)
    counts = count_points_in_boxes(points, boxes) if len(boxes) else np.zeros(0, np.int32)
    real = objects.type.astype(str) != "DontCare"
    plausibility.refuse_implausible(boxes, real, str(label_path), [frame_id] * len(boxes))
    table = BoxTable.from_arrays(
        np.full(len(boxes), frame_id, dtype=object),
        boxes,
        score=objects.score,
        label=objects.type,
        num_points=counts,
        **extra,
    )
    return points, table


def build_import(
    out: str | Path,
    layout: KittiLayout,
    frame_ids: list[str],
    crop_fov: bool = False,
    sensor: str = "kitti",
    progress: bool = True,
    intensity_max: float = 1.0,
    thinning: BeamThinning = BeamThinning(),
) -> BuildResult:
    """Stage body of `dali import kitti`: read every frame, write FrameSet + boxes into `out`
    (`progress`: a progress bar on stderr); reflectances are divided by `intensity_max`;
    `thinning`: the beams each scan keeps."""

    frames = (
        (frame_id, *load_frame(layout, frame_id, crop_fov, intensity_max, thinning))
        for frame_id in frame_ids
    )
    attrs = {"source_format": "kitti", "crop_fov": bool(crop_fov), **thinning.params()}
    notes = [
        "boxes: label_2 through calib (R0_rect, Tr_velo_to_cam) to the LiDAR frame, geometric centre",
        "DontCare rows: zero-size boxes at the origin; their 2D region is kept in bbox_*",
        *thinning.notes(),
    ]
    return write_imported(
        out, frames, sensor, attrs, len(frame_ids), notes=notes, progress=progress
    )


def find_calib_dir(root: str | Path, split: str = "training") -> Path:
    """The calib directory of a KITTI root: ROOT/SPLIT/calib, ROOT/calib, or ROOT itself."""
    root = Path(root)
    for candidate in (root / split / "calib", root / "calib"):
        if candidate.is_dir():
            return candidate
    if root.is_dir() and any(root.glob("*.txt")):
        return root
    raise ImportFormatError(
        f"{root}: no calib directory (looked for {root / split / 'calib'} and {root / 'calib'})"
    )
