"""Stage import_openpcdet: OpenPCDet's custom format (points/*.npy, labels/*.txt) -> a FrameSet
with boxes (dali_cli.importers.openpcdet)."""

from __future__ import annotations

from pathlib import Path
from typing import Unpack

from dali_cli.importers.common import ImportRun, check_sensor, run_import
from dali_cli.store.manifest import StageOutcome


def import_openpcdet(
    root: str | Path,
    out: str | Path,
    *,
    sensor: str,
    split: str | None = None,
    car_classes: tuple[str, ...] = (),
    intensity_max: float = 1.0,
    **run: Unpack[ImportRun],
) -> StageOutcome:
    """Import ROOT (the ids of ImageSets/`split`.txt, or every points/*.npy) into `out`."""
    from dali_cli.importers import openpcdet

    check_sensor(sensor, run)
    classes = tuple(car_classes) or openpcdet.DEFAULT_CAR_CLASSES
    frame_ids = openpcdet.frame_ids(root, split)
    root = Path(root)
    inputs = {"points": root / "points"}
    if (root / "labels").is_dir():
        inputs["labels"] = root / "labels"
    params = {
        "split": split,
        "car_classes": list(classes),
        "intensity_max": intensity_max,
        "sensor": sensor,
        "frames": len(frame_ids),
    }
    return run_import(
        "import-openpcdet",
        out,
        inputs,
        params,
        lambda tmp: openpcdet.build_import(
            tmp, root, frame_ids, classes, intensity_max, sensor, progress=run.get("progress", True)
        ),
        run,
    )
