"""Stage import_kitti_odometry: a KITTI odometry / SemanticKITTI sequence (velodyne, calib.txt,
times.txt, poses) -> an unlabeled FrameSet with its times and poses
(dali_cli.importers.kitti_odometry)."""

from __future__ import annotations

from pathlib import Path
from typing import Unpack

from dali_cli.importers.common import ImportRun, run_thinned_import, thinned_sensor
from dali_cli.runtime.errors import ParameterError
from dali_cli.store.manifest import StageOutcome


def import_kitti_odometry(
    sequence_dir: str | Path,
    out: str | Path,
    *,
    calib: str | Path | None = None,
    poses: str | Path | None = None,
    crop_fov: bool = False,
    crop_front_deg: float | None = None,
    sensor: str = "kitti",
    beams: int = 64,
    beams_azimuth_half: bool = False,
    **run: Unpack[ImportRun],
) -> StageOutcome:
    """Import the sequence SEQUENCE_DIR into `out`. Its calib (when present), times and poses
    are read and checked before anything is written."""
    from dali_cli.importers.common import check_point_files
    from dali_cli.importers.kitti_odometry import (
        OdometrySequence,
        build_import,
        read_odometry_calib,
    )

    thinning, sensor = thinned_sensor(sensor, beams, beams_azimuth_half, run)
    if crop_fov and crop_front_deg is not None:
        raise ParameterError(("crop_fov", "crop_front_deg"), "give one crop, not both")
    sequence = OdometrySequence.of(sequence_dir, calib, poses)
    if crop_fov and sequence.calib is None:
        raise ParameterError(
            "crop_fov",
            f"needs the camera calibration: {Path(sequence_dir) / 'calib.txt'} not found (give "
            "--calib FILE, or --crop-front-deg to crop by azimuth)",
        )
    frame_ids = sequence.frame_ids()
    check_point_files([sequence.velodyne_dir / f"{frame_id}.bin" for frame_id in frame_ids])
    camera = read_odometry_calib(sequence.calib) if sequence.calib is not None else None
    table = sequence.sequence_table(
        frame_ids, camera.Tr_velo_to_cam if camera is not None else None
    )
    inputs = {
        "velodyne": sequence.velodyne_dir,
        "calib": sequence.calib,
        "times": sequence.times,
        "poses": sequence.poses,
    }
    params = {
        "crop_fov": crop_fov,
        "crop_front_deg": crop_front_deg,
        "sensor": sensor,
        "frames": len(frame_ids),
    }

    def build(tmp, **common):
        return build_import(
            tmp, sequence, frame_ids, camera, table, crop_front_deg=crop_front_deg, **common
        )

    return run_thinned_import("import-kitti-odometry", out, inputs, params, run, thinning, build)
