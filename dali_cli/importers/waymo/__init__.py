"""Waymo Open Dataset import (v2 Parquet or v1 TFRecord), without TensorFlow (docs/data.md).

`build_import` is the stage body of `dali import waymo`: frames in the TOP LiDAR's frame, boxes
as dali boxes (Car for TYPE_VEHICLE; other types keep their names), num_points from the
dataset's `num_lidar_points_in_box`, per-segment counts for the manifest.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from dali_cli.importers.waymo.frame import (
    BOX_LABELS,
    TOP,
    WaymoFormatError,
    WaymoFrame,
    frame_id,
    scan_points,
    to_top_frame,
)

__all__ = ["WaymoFormatError", "WaymoSource", "build_import", "detect_format"]


def detect_format(root: Path) -> str:
    """'v2' when ROOT has a lidar/ component folder of Parquet files, 'v1' for *.tfrecord."""
    if any((root / "lidar").glob("*.parquet")):
        return "v2"
    if any(root.glob("*.tfrecord")):
        return "v1"
    raise WaymoFormatError(
        f"{root}: neither a Waymo v2 folder (lidar/*.parquet, lidar_calibration/, ...) nor v1 "
        "segment-*.tfrecord files (give --split for ROOT/SPLIT/...)"
    )


class WaymoSource:
    """The segments of one Waymo folder (ROOT or ROOT/SPLIT) in one format."""

    def __init__(self, root: Path, fmt: str = "auto", segments: list[str] | None = None):
        self.root = Path(root)
        self.format = detect_format(self.root) if fmt == "auto" else fmt
        if self.format == "v2":
            from dali_cli.importers.waymo import v2

            found = v2.list_segments(self.root)
        else:
            found = sorted(p.stem for p in self.root.glob("*.tfrecord"))
        if segments:
            unknown = sorted(set(segments) - set(found))
            if unknown:
                raise WaymoFormatError(f"{self.root}: no segment(s) {', '.join(unknown)}")
            found = [s for s in found if s in set(segments)]
        if not found:
            raise WaymoFormatError(f"{self.root}: no {self.format} segments")
        self.segments = found

    def frames(self, segment: str, returns: int, lidars: str, every: int) -> Iterator[WaymoFrame]:
        if self.format == "v2":
            from dali_cli.importers.waymo import v2

            yield from v2.read_segment(self.root, segment, returns, lidars, every)
            return
        from dali_cli.importers.waymo import v1

        for index, frame in enumerate(v1.read_segment(self.root / f"{segment}.tfrecord")):
            if index % every == 0:
                yield frame

    def input_paths(self) -> list[Path]:
        if self.format == "v1":
            return [self.root / f"{s}.tfrecord" for s in self.segments]
        return [self.root / c / f"{s}.parquet" for s in self.segments
                for c in ("lidar", "lidar_calibration") ]  # fmt: skip


def convert(frame: WaymoFrame, returns: int, lidars: str):
    """WaymoFrame → (frame id, points (n, 4) float32 TOP frame, BoxTable, points per laser)."""
    from dali_cli.importers.common import check_id
    from dali_cli.store.artifacts import BoxTable

    identifier = check_id(frame_id(frame.segment, frame.timestamp_micros), frame.where())
    points, per_laser = scan_points(frame, returns, lidars)
    points, boxes = to_top_frame(frame, points)
    labels = np.array([BOX_LABELS.get(int(t), f"TYPE_{int(t)}") for t in frame.types], object)
    table = BoxTable.from_arrays(
        [identifier] * len(boxes), boxes, label=labels, num_points=frame.num_points
    )
    return identifier, points, table, per_laser


def describe_top(frame: WaymoFrame) -> dict:
    """The TOP LiDAR's calibration in the units of sensors.toml (degrees, metres), for a real
    sensor profile: beam elevations lowest first, mount height above the vehicle origin."""
    top = frame.calibrations[TOP]
    if top.inclinations is not None:
        elevations = np.degrees(top.inclinations)
    else:
        elevations = np.degrees([top.inclination_min, top.inclination_max])
    return {
        "top_elevations_deg": [round(float(v), 4) for v in elevations],
        "top_mount_height_m": round(float(top.extrinsic[2, 3]), 4),
    }


def build_import(
    tmp: Path,
    source: WaymoSource,
    *,
    returns: int,
    lidars: str,
    every: int,
    sensor: str,
    progress: bool = True,
):
    """Write the chosen frames of every segment into `tmp` (the stage's temporary directory);
    `progress`: a progress bar on stderr."""
    from dali_cli.importers.common import write_imported

    per_segment: dict[str, dict] = {}
    started = time.perf_counter()

    def frames():
        for segment in source.segments:
            counts = per_segment.setdefault(segment, {"frames": 0, "points": 0, "boxes": 0})
            for frame in source.frames(segment, returns, lidars, every):
                identifier, points, table, _ = convert(frame, returns, lidars)
                if not top_calibration:
                    top_calibration.update(describe_top(frame))
                counts["frames"] += 1
                counts["points"] += len(points)
                counts["boxes"] += len(table)
                yield identifier, points, table

    top_calibration = {}
    result = write_imported(tmp, frames(), sensor, attrs={"source": "waymo", "format":
                            source.format, "lidars": lidars, "returns": returns},
                            description=f"waymo {source.format}", progress=progress)  # fmt: skip
    seconds = time.perf_counter() - started
    result.counts["segments"] = per_segment
    result.timings = {"frames_per_second": round(result.counts["frames"] / max(seconds, 1e-9), 3)}
    result.extra = {"waymo": {"format": source.format, "top_laser": TOP, **top_calibration}}
    return result
