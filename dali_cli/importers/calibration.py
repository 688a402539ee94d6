"""The camera calibration a user hands a command (`--calib` of `dali detect` and `dali eval`):
one KITTI calib .txt for every frame, a raw drive's date folder (its calib_*.txt files), or a
folder of per-frame <frame>.txt files of KITTI's object layout."""

from __future__ import annotations

from pathlib import Path

from dali_cli.importers.common import ImportFormatError
from dali_cli.importers.kitti import Calibration
from dali_cli.runtime.errors import StageError

# a KITTI raw drive's date folder holds its calibration as these files (the first two needed)
RAW_CALIB_FILES = ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt")
TAKES = (
    "--calib takes a KITTI object calib file (P2, R0_rect, Tr_velo_to_cam), a KITTI raw date "
    f"folder holding {' and '.join(RAW_CALIB_FILES[:2])}, or a folder of <frame>.txt calib files"
)


def load_calib(calib: Path | None) -> Calibration | Path | None:
    """A kitti.Calibration for every frame (a KITTI calib .txt, or a raw drive's date folder),
    the directory of per-frame <frame>.txt files, or None."""
    from dali_cli.importers.kitti import read_calib
    from dali_cli.importers.kitti_raw import read_raw_calib

    if calib is None:
        return None
    calib = Path(calib)
    if calib.is_file():
        if calib.name in RAW_CALIB_FILES:
            raise StageError(
                f"{calib}: one file of a KITTI raw drive's calibration; pass its date folder "
                f"({calib.parent}, holding {' and '.join(RAW_CALIB_FILES[:2])}) instead"
            )
        try:
            return read_calib(calib)
        except ImportFormatError as error:
            raise ImportFormatError(f"{error}; {TAKES}") from None
    if (calib / RAW_CALIB_FILES[0]).is_file():
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
