"""The scans a model is for: the sensor profile, mount height and front view of the frame set a
training stage fits it to, recorded in model.json's `config` (`sensor`, `mount_height_m`,
`front_deg`).

pretrain takes them from its source; the stages that adapt a model to a target (retrain on the
target's PPCG frames, self-train on the target's own) from the target. `Detector.predict`,
`OnnxDetector.predict` and `dali detect` use them unless told otherwise, so a scan without a
sensor of its own (.pcd, .npy) is read at the ground of the sensor the model was adapted to, not
its source's, and is cropped to the view the model was adapted on.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from dali_cli.detector.config import DetectorConfig

# `--crop-fov` (dali import kitti, kitti-raw, kitti-odometry) keeps the points that project into
# KITTI camera 2's image, about 82 degrees of azimuth wide (Makefile REAL_FRONT_DEG: the same view)
CAMERA_VIEW_DEG = 82.0


def cropped_front_deg(attrs: dict) -> float | None:
    """The front view (degrees of azimuth about +x) a frame set's points were cropped to, from
    its attrs: `crop_front_deg`, else CAMERA_VIEW_DEG for `crop_fov`; for a merge (`drives`),
    the widest of its parts when every part was cropped; None for full scans."""
    drives = attrs.get("drives")
    if isinstance(drives, dict) and drives:
        views = [cropped_front_deg(part) if isinstance(part, dict) else None
                 for part in drives.values()]  # fmt: skip
        return None if None in views else max(views)
    front = attrs.get("crop_front_deg")
    if isinstance(front, int | float) and not isinstance(front, bool):
        return float(front) if math.isfinite(front) and 0 < front <= 360 else None
    return CAMERA_VIEW_DEG if attrs.get("crop_fov") is True else None


def for_scans_of(
    config: DetectorConfig, data_dir: str | Path, sensors_path: str | Path | None = None
) -> DetectorConfig:
    """`config` for the scans of the frame set `data_dir`: its sensor profile, that profile's
    mount height (sensors.toml, m) and its cropped front view (None: full scans). An
    ArtifactError when the frame set names no sensor."""
    from dali_cli.sensors import get_profile
    from dali_cli.store.artifacts import ArtifactError, FrameSet

    frames = FrameSet(data_dir)
    if not frames.sensor:
        raise ArtifactError(f"{frames.path}: attrs has no 'sensor' (needed for the mount height)")
    return dataclasses.replace(
        config,
        sensor=frames.sensor,
        mount_height_m=get_profile(frames.sensor, sensors_path).mount_height_m,
        front_deg=cropped_front_deg(frames.attrs),
    )
