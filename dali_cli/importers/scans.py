"""A user's own LiDAR scans, as they hold them: find them and read each into dali's sensor frame.

SCANS may be one scan file or a folder of them (KITTI `.bin`, PCD as PCL and ROS write it, ascii or
binary, nuScenes `.pcd.bin`, `.npy`), a KITTI raw drive (`velodyne_points/data/*.bin`), a KITTI
object split (`velodyne/*.bin`) or a dali frame set. Every scan comes out `(n, 4)` float32 x, y, z
(metres, x forward, y left, z up: nuScenes' x-right clouds are turned) and intensity. Bad input is
an ImportFormatError naming the file: a size that is no multiple of the record, a PCD without
x, y, z, a non-numeric array, no scan at all.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dali_cli.importers.common import ImportFormatError, check_finite_points, read_float_records
from dali_cli.runtime.limits import check_limit
from dali_cli.store.regular_files import check_regular

SUFFIXES = (".pcd.bin", ".bin", ".pcd", ".npy")
INTENSITY_FIELDS = ("intensity", "i", "reflectance", "remission")
PCD_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4",
             ("I", 8): "<i8", ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8"}  # fmt: skip
MAX_PCD_HEADER_BYTES = 64 * 1024


@dataclass(frozen=True)
class ScanFile:
    """One scan: its frame id (the file's stem), path and format ("kitti-bin", "nuscenes-bin",
    "pcd", "npy")."""

    frame_id: str
    path: Path
    kind: str


def scan_kind(path: Path) -> str | None:
    """The format of a scan file by its name, or None for another file."""
    name = path.name.lower()
    if name.endswith(".pcd.bin"):
        return "nuscenes-bin"
    return {".bin": "kitti-bin", ".pcd": "pcd", ".npy": "npy"}.get(path.suffix.lower())


def frame_id_of(path: Path) -> str:
    name = path.name
    for suffix in SUFFIXES:
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return path.stem


def find_scans(scans: str | Path) -> list[ScanFile]:
    """The scan files of SCANS, sorted by name (see the module docstring; a dali frame set is
    handled by the caller). ImportFormatError when there is none, or two share a frame id."""
    root = Path(scans)
    if root.is_file():
        kind = scan_kind(root)
        if kind is None:
            raise ImportFormatError(
                f"{root}: not a scan file (expected one of {', '.join(SUFFIXES)})"
            )
        return [ScanFile(frame_id_of(root), root, kind)]
    folder = root
    for inner in ("velodyne_points/data", "velodyne"):  # a KITTI raw drive, an object split
        if (root / inner).is_dir():
            folder = root / inner
            break
    found = [
        ScanFile(frame_id_of(path), path, kind)
        for path in sorted(folder.iterdir())
        if path.is_file() and (kind := scan_kind(path)) is not None
    ]
    if not found:
        raise ImportFormatError(
            f"{folder}: no scan files ({', '.join(SUFFIXES)}) in this folder, nor a KITTI raw "
            "drive (velodyne_points/data) or object split (velodyne)"
        )
    ids = [scan.frame_id for scan in found]
    if len(set(ids)) != len(ids):
        twice = sorted({i for i in ids if ids.count(i) > 1})[0]
        raise ImportFormatError(f"{folder}: two scans share the frame id '{twice}'")
    return found


def read_scan(scan: ScanFile) -> np.ndarray:
    """`(n, 4)` float32 x, y, z, intensity of one scan in dali's sensor frame (x forward)."""
    if scan.kind == "kitti-bin":
        return read_float_records(scan.path, 4)
    if scan.kind == "nuscenes-bin":
        records = read_float_records(scan.path, 5)
        points = records[:, :4].copy()
        points[:, 0], points[:, 1] = records[:, 1], -records[:, 0]  # x right -> x forward
        return points
    if scan.kind == "npy":
        return read_npy(scan.path)
    return read_pcd(scan.path)


def read_npy(path: Path) -> np.ndarray:
    """A `.npy` cloud `(n, >=3)` of real numbers -> `(n, 4)` float32 (intensity 0 when absent)."""
    check_regular(path, "point file")
    check_limit("point_file_bytes", path.stat().st_size, str(path))
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as error:
        raise ImportFormatError(f"{path}: cannot read .npy ({error})") from None
    if array.ndim != 2 or array.shape[1] < 3 or array.dtype.kind not in "iuf":
        raise ImportFormatError(
            f"{path}: expected a numeric (n, >=3) array (x, y, z[, intensity]), got "
            f"{array.dtype} {array.shape}"
        )
    points = np.zeros((len(array), 4), np.float32)
    points[:, : min(4, array.shape[1])] = array[:, :4]
    check_finite_points(points, path)
    return points


def pcd_header(raw: bytes, path: Path) -> tuple[dict[str, list[str]], int]:
    """The header fields of a PCD file (key -> values) and the byte offset of its data."""
    fields: dict[str, list[str]] = {}
    offset = 0
    while offset < min(len(raw), MAX_PCD_HEADER_BYTES):
        end = raw.find(b"\n", offset)
        end = len(raw) if end < 0 else end
        line = raw[offset:end].decode("ascii", "replace").strip()
        offset = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        fields[key.upper()] = values
        if key.upper() == "DATA":
            return fields, offset
    raise ImportFormatError(f"{path}: not a PCD file (no DATA line in its header)")


def read_pcd(path: Path) -> np.ndarray:
    """A PCD file (ascii or binary, as PCL and ROS write it) -> `(n, 4)` float32 x, y, z and the
    intensity field when there is one (intensity, i, reflectance or remission; else 0)."""
    check_regular(path, "point file")
    check_limit("point_file_bytes", path.stat().st_size, str(path))
    raw = path.read_bytes()
    header, offset = pcd_header(raw, path)
    names = [name.lower() for name in header.get("FIELDS", [])]
    missing = [axis for axis in "xyz" if axis not in names]
    if missing:
        raise ImportFormatError(
            f"{path}: PCD without the field{'s' if len(missing) > 1 else ''} {', '.join(missing)} "
            f"(FIELDS {' '.join(names) or 'none'})"
        )
    try:
        sizes = [int(v) for v in header["SIZE"]]
        types = [v.upper() for v in header["TYPE"]]
        counts = [int(v) for v in header.get("COUNT", ["1"] * len(names))]
        total = int(
            header.get("POINTS", [None])[0] or int(header["WIDTH"][0]) * int(header["HEIGHT"][0])
        )
        dtypes = [PCD_TYPES[(kind, size)] for kind, size in zip(types, sizes, strict=True)]
    except (KeyError, ValueError, IndexError) as error:
        raise ImportFormatError(
            f"{path}: PCD header with a bad SIZE, TYPE, COUNT or POINTS ({error})"
        ) from None
    if len(counts) != len(names) or total < 0:
        raise ImportFormatError(f"{path}: PCD header's FIELDS, SIZE, TYPE and COUNT disagree")
    mode = header["DATA"][0].lower() if header["DATA"] else ""
    columns = [(f"{name}_{k}" if count > 1 else name, dtype) for name, dtype, count in
               zip(names, dtypes, counts, strict=True) for k in range(count)]  # fmt: skip
    if mode == "binary":
        record = np.dtype([(name, dtype) for name, dtype in columns])
        if len(raw) - offset < total * record.itemsize:
            raise ImportFormatError(
                f"{path}: binary PCD of {total} points of {record.itemsize} bytes needs "
                f"{total * record.itemsize} bytes of data, has {len(raw) - offset} (truncated)"
            )
        data = np.frombuffer(raw, record, count=total, offset=offset)
        table = {name: data[name].astype(np.float64) for name, _ in columns}
    elif mode == "ascii":
        try:
            text = raw[offset:].decode("ascii")
            values = np.array(text.split(), dtype=np.float64).reshape(-1, len(columns))
        except (UnicodeDecodeError, ValueError):
            raise ImportFormatError(
                f"{path}: ascii PCD data is not {len(columns)} numbers a point"
            ) from None
        table = {name: values[:, k] for k, (name, _) in enumerate(columns)}
    else:
        raise ImportFormatError(
            f"{path}: PCD DATA {mode or '(none)'} is not read (ascii or binary; convert a "
            "binary_compressed file with pcl_convert_pcd_ascii_binary)"
        )
    intensity = next((table[name] for name in INTENSITY_FIELDS if name in table), None)
    points = np.zeros((len(table["x"]), 4), np.float32)
    points[:, 0], points[:, 1], points[:, 2] = table["x"], table["y"], table["z"]
    if intensity is not None:
        points[:, 3] = intensity
    keep = np.isfinite(points[:, :3]).all(axis=1)  # PCL marks missing returns NaN (organized)
    return points[keep]
