"""The camera calibration a user hands a command (`--calib` of `dali detect` and `dali eval`):
one KITTI calib .txt for every frame, a raw drive's date folder (its calib_*.txt files), or a
folder of per-frame <frame>.txt files of KITTI's object layout."""

from __future__ import annotations

from pathlib import Path

from dali_cli.importers.kitti import Calibration
from dali_cli.runtime.errors import StageError


def load_calib(calib: Path | None) -> Calibration | Path | None:
    """A kitti.Calibration for every frame (a KITTI calib .txt, or a raw drive's date folder),
    the directory of per-frame <frame>.txt files, or None."""
    from dali_cli.importers.kitti import read_calib
    from dali_cli.importers.kitti_raw import read_raw_calib

    if calib is None:
        return None
    calib = Path(calib)
    if calib.is_file():
        return read_calib(calib)
    if (calib / "calib_cam_to_cam.txt").is_file():
        return read_raw_calib(calib)[0]
    return calib


def frame_calib(calib: Calibration | Path, frame_id: str) -> Calibration:
    """The calibration of one frame of `load_calib`'s result (StageError naming the missing
    file)."""
    from dali_cli.importers.kitti import read_calib

    if not isinstance(calib, Path):
        return calib
    path = calib / f"{frame_id}.txt"
    if not path.is_file():
        raise StageError(f"{path}: calib file missing for frame '{frame_id}'")
    return read_calib(path)
