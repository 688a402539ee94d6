"""Stage import_kitti: KITTI object data (velodyne, label_2, calib) -> a FrameSet with boxes
(dali_cli.importers.kitti)."""

from __future__ import annotations

from pathlib import Path
from typing import Unpack

from dali_cli.importers.common import ImportRun, run_thinned_import, thinned_sensor
from dali_cli.store.manifest import StageOutcome


def import_kitti(
    root: str | Path,
    out: str | Path,
    *,
    split: str = "training",
    ids_path: str | Path | None = None,
    label_dir: str | Path | None = None,
    crop_fov: bool = False,
    sensor: str = "kitti",
    beams: int = 64,
    beams_azimuth_half: bool = False,
    intensity_max: float = 1.0,
    **run: Unpack[ImportRun],
) -> StageOutcome:
    """Import ROOT[/split] (every scan, or the ids of `ids_path`) into `out`."""
    from dali_cli.importers.common import check_point_files, read_id_list
    from dali_cli.importers.kitti import KittiLayout, build_import
    from dali_cli.store.regular_files import check_present_files

    thinning, sensor = thinned_sensor(sensor, beams, beams_azimuth_half, run)
    layout = KittiLayout.of(root, split, label_dir)
    frame_ids = layout.frame_ids(read_id_list(ids_path) if ids_path else None)
    check_point_files([layout.velodyne_dir / f"{frame_id}.bin" for frame_id in frame_ids])
    check_present_files([layout.label_dir / f"{i}.txt" for i in frame_ids], "label file", "label")
    check_present_files([layout.calib_dir / f"{i}.txt" for i in frame_ids], "calib file", "calib")
    inputs = {"velodyne": layout.velodyne_dir, "ids": ids_path}
    for name, path in (("labels", layout.label_dir), ("calib", layout.calib_dir)):
        if path.is_dir():
            inputs[name] = path
    params = {"split": split, "crop_fov": crop_fov, "sensor": sensor, "frames": len(frame_ids),
              "intensity_max": intensity_max}  # fmt: skip

    def build(tmp, **common):
        return build_import(tmp, layout, frame_ids, intensity_max=intensity_max, **common)

    return run_thinned_import("import-kitti", out, inputs, params, run, thinning, build)
