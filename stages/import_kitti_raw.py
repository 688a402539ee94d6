"""Stage import_kitti_raw: a KITTI raw synced drive (velodyne_points, the day's calib files,
tracklet_labels.xml; with poses the OXTS records) -> a FrameSet with boxes and, with poses, its
sequence table (dali_cli.importers.kitti_raw)."""

from __future__ import annotations

from pathlib import Path
from typing import Unpack

from dali_cli.importers.common import ImportRun, run_thinned_import, thinned_sensor
from dali_cli.store.manifest import StageOutcome


def import_kitti_raw(
    drive_dir: str | Path,
    out: str | Path,
    *,
    calib_dir: str | Path | None = None,
    tracklets: str | Path | None = None,
    labels: bool = True,
    crop_fov: bool = False,
    sensor: str = "kitti",
    beams: int = 64,
    beams_azimuth_half: bool = False,
    poses: bool = False,
    **run: Unpack[ImportRun],
) -> StageOutcome:
    """Import the drive DRIVE_DIR into `out` (with its tracklets unless `labels` is False; with
    the scans' LiDAR poses from the OXTS records when `poses`)."""
    from dali_cli.importers.kitti_raw import RawDrive, build_import

    thinning, sensor = thinned_sensor(sensor, beams, beams_azimuth_half, run)
    drive = RawDrive.of(drive_dir, calib_dir, tracklets, labels)
    frame_ids = drive.frame_ids()
    inputs = {
        "velodyne": drive.velodyne_dir,
        "calib_cam_to_cam": drive.calib_dir / "calib_cam_to_cam.txt",
        "calib_velo_to_cam": drive.calib_dir / "calib_velo_to_cam.txt",
        "tracklets": drive.tracklets,
    }
    if poses:  # recorded only when asked for: imports made without poses stay up to date
        inputs.update({"oxts": drive.oxts_dir, "calib_imu_to_velo": drive.imu_to_velo_file})
    params = {
        "labels": drive.tracklets is not None,
        "crop_fov": crop_fov,
        "sensor": sensor,
        "frames": len(frame_ids),
        **({"poses": "oxts"} if poses else {}),
    }

    def build(tmp, **common):
        return build_import(tmp, drive, frame_ids, poses=poses, **common)

    return run_thinned_import("import-kitti-raw", out, inputs, params, run, thinning, build)
