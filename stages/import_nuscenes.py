"""Stage import_nuscenes: nuScenes LIDAR_TOP key frames (JSON tables, or LiDAR-frame boxes of a
CSV) -> a FrameSet with boxes (dali_cli.importers.nuscenes)."""

from __future__ import annotations

from pathlib import Path
from typing import Unpack

from dali_cli.importers.common import ImportRun, check_sensor, run_import
from dali_cli.runtime.errors import ParameterError
from dali_cli.store.manifest import StageOutcome


def import_nuscenes(
    path: str | Path,
    out: str | Path,
    *,
    version: str = "v1.0-mini",
    boxes_csv: str | Path | None = None,
    scenes: str | None = None,
    car_categories: tuple[str, ...] = (),
    max_frames: int | None = None,
    lidar_frame: bool = False,
    sensor: str = "nuscenes",
    **run: Unpack[ImportRun],
) -> StageOutcome:
    """Import the nuScenes data at `path` into `out` (x forward unless `lidar_frame`)."""
    from dali_cli.importers import nuscenes

    check_sensor(sensor, run)
    categories = tuple(car_categories) or nuscenes.DEFAULT_CAR_CATEGORIES
    if boxes_csv:
        if scenes:
            raise ParameterError(("scenes", "boxes_csv"), "scenes need the JSON tables, not a CSV")
        source = nuscenes.CsvSource.of(path, boxes_csv)
        inputs = {"points": path, "boxes_csv": boxes_csv}
    else:
        source = nuscenes.JsonSource.of(path, version, scenes.split(",") if scenes else None)
        inputs = {"tables": source.table_dir, "points": source.lidar_dir()}
    samples = source.samples()[:max_frames] if max_frames else source.samples()
    params = {
        "version": None if boxes_csv else version,
        "car_categories": list(categories),
        "scenes": scenes,
        "max_frames": max_frames,
        "x_forward": not lidar_frame,
        "sensor": sensor,
    }
    return run_import(
        "import-nuscenes",
        out,
        inputs,
        params,
        lambda tmp: nuscenes.build_import(
            tmp,
            source,
            samples,
            categories,
            x_forward=not lidar_frame,
            sensor=sensor,
            progress=run.get("progress", True),
        ),
        run,
    )
