"""Stage import_waymo: Waymo Open Dataset v2 Parquet or v1 TFRecord -> a FrameSet with boxes
(dali_cli.importers.waymo; no TensorFlow)."""

from __future__ import annotations

from pathlib import Path
from typing import Unpack

from dali_cli.importers.common import ImportRun, check_sensor, run_import
from dali_cli.runtime.errors import ParameterError, StageError
from dali_cli.store.manifest import StageOutcome


def import_waymo(
    root: str | Path,
    out: str | Path,
    *,
    fmt: str = "auto",
    split: str | None = None,
    every: int = 1,
    lidars: str = "top",
    returns: int = 1,
    segments: str | None = None,
    sensor: str = "waymo",
    **run: Unpack[ImportRun],
) -> StageOutcome:
    """Import ROOT[/split] (every `every`-th frame of each segment, or of `segments`) into `out`."""
    from dali_cli.importers.waymo import WaymoFormatError, WaymoSource, build_import

    check_sensor(sensor, run)
    folder = Path(root) / split if split else Path(root)
    if not folder.is_dir():
        raise ParameterError("split", f"{folder}: no such folder")
    try:
        source = WaymoSource(folder, fmt, segments.split(",") if segments else None)
    except WaymoFormatError as error:
        raise StageError(str(error)) from None
    params = {"format": source.format, "split": split, "every": every, "lidars": lidars,
              "returns": returns, "segments": source.segments, "sensor": sensor}  # fmt: skip

    def build(tmp):
        try:
            return build_import(
                tmp,
                source,
                returns=returns,
                lidars=lidars,
                every=every,
                sensor=sensor,
                progress=run.get("progress", True),
            )
        except WaymoFormatError as error:
            raise StageError(str(error)) from None

    return run_import(
        "import-waymo",
        out,
        {"segments": source.input_paths()},
        params,
        build,
        run,
    )
