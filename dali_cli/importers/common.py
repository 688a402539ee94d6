"""Shared pieces of the importers: the error type, raw float32 point files, id lists, writing."""

from __future__ import annotations

from pathlib import Path
from typing import TypedDict

import numpy as np

from dali_cli.runtime.errors import StageError
from dali_cli.runtime.limits import check_limit
from dali_cli.store.frame_ids import name_problem
from dali_cli.store.regular_files import check_regular


class ImportFormatError(StageError):
    """Malformed input data; the message names the file, the line or point, and the field."""


def read_float_records(path: str | Path, fields: int) -> np.ndarray:
    """Read a raw little-endian float32 file of `fields` values per point.

    Returns `(n, fields)` float32. Raises ImportFormatError when the size is not a multiple of
    `4 * fields` bytes (a truncated file) or when a point holds NaN/inf (naming the point).
    """
    path = Path(path)
    try:
        if path.is_dir():
            raise ImportFormatError(f"{path}: a directory, not a point file")
        check_regular(path, "point file")
        check_limit("point_file_bytes", path.stat().st_size, str(path))
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ImportFormatError(f"{path}: point file not found") from None
    except OSError as error:
        raise ImportFormatError(f"{path}: cannot read point file ({error})") from None
    record = 4 * fields
    if len(raw) % record:
        raise ImportFormatError(
            f"{path}: size {len(raw)} bytes is not a multiple of {record} "
            f"({fields} float32 values per point); the file is truncated or has another layout"
        )
    points = np.frombuffer(raw, dtype="<f4").reshape(-1, fields).astype(np.float32)
    check_finite_points(points, path)
    return points


MAX_POINT_DISTANCE_M = 1000.0  # no LiDAR return lies a kilometre away along any axis


def check_scan_contract(points: np.ndarray, path: str | Path, intensity_max: float = 1.0):
    """`points (n, 4)` of one scan file as the frame-set contract holds them: intensity divided
    by `intensity_max` and within [0, 1], coordinates within MAX_POINT_DISTANCE_M of the sensor,
    at least one point off the sensor's origin. ImportFormatError naming the file and what was
    found otherwise (a text file or a scan in millimetres read as floats is no scan). Returns
    the points (a copy when rescaled)."""
    if len(points) == 0 or not np.any(points[:, :3]):
        raise ImportFormatError(
            f"{path}: no valid point ({len(points)} points, none off the sensor's origin)"
        )
    reach = float(np.abs(points[:, :3]).max())
    if reach > MAX_POINT_DISTANCE_M:
        raise ImportFormatError(
            f"{path}: coordinates up to {reach:.3g} m, beyond any LiDAR's reach "
            f"({MAX_POINT_DISTANCE_M:g} m): not a scan of float32 metres?"
        )
    if intensity_max != 1.0:
        points = points.copy()
        points[:, 3] /= intensity_max
    low, high = float(points[:, 3].min()), float(points[:, 3].max())
    if low < 0.0 or high > 1.0:
        hint = f" after dividing by {intensity_max:g}" if intensity_max != 1.0 else ""
        raise ImportFormatError(
            f"{path}: intensity from {low:.4g} to {high:.4g}{hint}, outside [0, 1] (the frame "
            "set's contract); for 8-bit intensities give --intensity-max 255"
        )
    return points


def check_point_files(paths: list[Path]) -> None:
    """Every point file within the size limit (a stat each), before the stage hashes or reads
    them: an oversized file fails at once instead of after hashing gigabytes."""
    for path in paths:
        try:
            size = check_regular(path, "point file").stat().st_size
        except OSError:
            continue  # missing files are named where they are read
        check_limit("point_file_bytes", size, str(path))


def check_finite_points(points: np.ndarray, path: str | Path) -> None:
    """Raise ImportFormatError naming the first point (0-based) with a NaN/inf value."""
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        raise ImportFormatError(
            f"{path}: point {bad} has NaN/inf values ({int((~finite).sum())} bad points in all)"
        )


def read_text_lines(path: str | Path, what: str, kind: str = "calib") -> list[str]:
    """The lines of a UTF-8 text file of `kind` (regular_files.BUDGETS: its size budget);
    ImportFormatError naming the file (and `what` it should be) when it is missing, not a
    regular file, over the budget or not UTF-8 text (the first bad byte's offset)."""
    from dali_cli.store.regular_files import UnreadableFileError, read_text_file

    try:
        return read_text_file(path, what, kind).splitlines()
    except UnreadableFileError as error:
        raise ImportFormatError(str(error)) from None
    except OSError as error:
        raise ImportFormatError(f"{path}: cannot read {what} ({error.strerror})") from None


def read_keyed(path: Path) -> dict[str, tuple[int, str]]:
    """`KEY: values` lines of a raw calib file -> {key: (line number, value text)}."""
    values = {}
    for number, line in enumerate(read_text_lines(path, "calib file"), start=1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:
            raise ImportFormatError(f"{path}, line {number}: expected 'KEY: values', got {line!r}")
        values[key.strip()] = (number, rest)
    return values


def keyed_matrix(path: Path, values: dict, key: str, shape: tuple[int, int]) -> np.ndarray:
    """The `shape` float64 matrix of `key`; errors name the file, line and key."""
    if key not in values:
        raise ImportFormatError(f"{path}: calib key '{key}' missing")
    number, text = values[key]
    try:
        numbers = np.array([float(v) for v in text.split()], dtype=np.float64)
    except ValueError:
        raise ImportFormatError(f"{path}, line {number}: '{key}' has a non-numeric value") from None
    size = shape[0] * shape[1]
    if numbers.size != size:
        raise ImportFormatError(
            f"{path}, line {number}: '{key}' has {numbers.size} values, expected {size}"
        )
    if not np.isfinite(numbers).all():
        raise ImportFormatError(f"{path}, line {number}: '{key}' has NaN/inf values")
    return numbers.reshape(shape)


def read_id_list(path: str | Path) -> list[str]:
    """Frame ids from a text file, one per line (blank lines and `#` comments ignored).

    Each id must be able to name a file (dali_cli.store.frame_ids: no path separators, `..`, control
    characters; at most 200 bytes): ids become file names in exports, and an id such as
    `../../other/velodyne/000008` would otherwise read and later write outside the dataset.
    Errors name the file and the line."""
    path = Path(path)
    lines = read_text_lines(path, "id list", "ids")
    ids, first_line = [], {}
    for number, line in enumerate(lines, start=1):
        frame_id = line.split("#", 1)[0].strip()
        if not frame_id:
            continue
        check_id(frame_id, f"{path}, line {number}")
        if frame_id in first_line:
            raise ImportFormatError(
                f"{path}, line {number}: duplicate frame id '{frame_id}' "
                f"(first on line {first_line[frame_id]})"
            )
        first_line[frame_id] = number
        ids.append(frame_id)
    if not ids:
        raise ImportFormatError(f"{path}: the id list names no frame (an empty set is no import)")
    return ids


def indexed_scan_ids(directory: Path, what: str = "scan index") -> list[str]:
    """Every `directory/*.bin` stem, each a whole scan index (digits only), sorted as text (the
    datasets zero-pad them); ImportFormatError naming the file, or the directory without scans."""
    ids = []
    for path in sorted(directory.glob("*.bin")):
        check_id(path.stem, f"{path}: file name")
        if not path.stem.isdigit():
            raise ImportFormatError(f"{path}: file name is not a {what}")
        ids.append(path.stem)
    if not ids:
        raise ImportFormatError(f"{directory}: no .bin scans")
    return ids


def check_id(frame_id: str, where: str) -> str:
    """`frame_id` if it can name a file, else ImportFormatError `"<where>: frame id ..."`."""
    problem = name_problem(frame_id)
    if problem is not None:
        raise ImportFormatError(f"{where}: frame id {problem}")
    return frame_id


def write_imported(
    out: str | Path,
    frames,
    sensor: str,
    attrs: dict | None = None,
    total: int | None = None,
    description: str | None = None,
    notes: list[str] | None = None,
    progress: bool = True,
):
    """Write `(frame_id, points (n, 4), BoxTable | None)` triples as a FrameSet + boxes.parquet
    (`progress`: a progress bar of `total` frames on stderr, named `description`; by default
    "import " and the attrs' source_format).

    A frame whose table is None has no labels; when no frame has labels, no box table is written
    (an unlabelled set). Returns the manifest's BuildResult (counts, notes). `out` is the stage's
    temporary directory.
    """
    from tqdm import tqdm

    from dali_cli.store.artifacts import BoxTable, FrameSetWriter, write_boxes
    from dali_cli.store.manifest import BuildResult

    if description is None:
        description = f"import {(attrs or {}).get('source_format', '')}".rstrip()
    tables = []
    unlabeled = 0
    with FrameSetWriter(out, sensor=sensor, attrs=attrs) as writer:
        for frame_id, points, table in tqdm(
            frames, total=total, desc=description, unit="frame", disable=not progress, leave=False
        ):
            writer.append(frame_id, points)
            if table is None:
                unlabeled += 1
            else:
                tables.append(table)
    if writer.count == 0:
        raise ImportFormatError(f"{description}: no frame to import (an empty frame set is none)")
    counts = {
        "frames": writer.count,
        "points": int(writer.num_points),
        "frames_without_labels": unlabeled,
    }
    if tables:
        boxes = BoxTable.concat(tables)
        write_boxes(out, boxes)
        labels, per_label = np.unique(boxes["label"].astype(str), return_counts=True)
        counts["boxes"] = len(boxes)
        counts["boxes_by_label"] = {str(k): int(v) for k, v in zip(labels, per_label, strict=True)}
    return BuildResult(counts=counts, notes=list(notes or []))


class ImportRun(TypedDict, total=False):
    """What every import stage takes besides its source and options: a sensors.toml to use
    instead of the project's, the stage runner's force / dry_run, and progress (a progress bar
    on stderr; default on)."""

    sensors_path: str | None
    force: bool
    dry_run: bool
    progress: bool


def check_sensor(sensor: str, run: ImportRun) -> None:
    """An unknown sensor profile fails before any work (sensors.get_profile's error)."""
    from dali_cli.sensors import get_profile

    get_profile(sensor, run.get("sensors_path"))


def run_import(stage: str, out, inputs: dict, params: dict, build, run: ImportRun):
    """store.manifest.run_stage of an import stage with its `run` flags: the StageOutcome."""
    from dali_cli.store.manifest import run_stage

    force, dry_run = run.get("force", False), run.get("dry_run", False)
    return run_stage(stage, out, inputs, params, build, force=force, dry_run=dry_run)


def thinned_sensor(sensor: str, beams: int, azimuth_half: bool, run: ImportRun):
    """The BeamThinning of a KITTI import's --beams options and the sensor profile its frames
    get (kitti -> kitti-16 with --beams 16), checked: an unknown profile fails before any work."""
    from dali_cli.importers.beams import BeamThinning

    thinning = BeamThinning.of(beams, azimuth_half)
    sensor = thinning.sensor(sensor)
    check_sensor(sensor, run)
    return thinning, sensor


def run_thinned_import(
    stage: str, out, inputs: dict, params: dict, run: ImportRun, thinning, build
):
    """run_import of a KITTI import whose scans `thinning` thins (its parameters join `params`):
    `build(tmp, **common)` writes the frame set, common being the crop_fov and sensor recorded in
    `params`, `thinning` and the progress flag of `run`."""
    common = {"crop_fov": params["crop_fov"], "sensor": params["sensor"], "thinning": thinning,
              "progress": run.get("progress", True)}  # fmt: skip
    return run_import(
        stage, out, inputs, params | thinning.params(), lambda tmp: build(tmp, **common), run
    )
