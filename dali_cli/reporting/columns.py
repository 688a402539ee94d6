"""The figures of a run's report.json that tables show, and their statistics over runs.

`COLUMNS` names each figure and where it sits in a report row; `dig` reads it; `statistics` is
the mean ± sample standard deviation over runs. Shared by aggregate, paired and compare.
"""

from __future__ import annotations

import math

import numpy as np

from dali_cli.reporting.report import BANDS, DIFFICULTIES

# (column title, how to read it from a row of report.json)
COLUMNS: tuple[tuple[str, tuple], ...] = (
    ("BEV@0.7", ("ap", "0.7", "bev")),
    ("3D@0.7", ("ap", "0.7", "3d")),
    ("APH@0.7", ("ap", "0.7", "aph")),
    ("BEV@0.5", ("ap", "0.5", "bev")),
    ("3D@0.5", ("ap", "0.5", "3d")),
    *((f"KITTI 3D@0.7 {d}", ("kitti", "0.7", "3d", d)) for d in DIFFICULTIES),
    ("KITTI BEV@0.7 moderate", ("kitti", "0.7", "bev", "moderate")),
    ("pred l", ("sizes", "pred", 0)),
    ("pred w", ("sizes", "pred", 1)),
    ("pred h", ("sizes", "pred", 2)),
    ("scale", ("scale",)),
    *((f"3D@0.7 {band} m", ("bands", band, "3d")) for band in BANDS),
)


def dig(row: dict, keys: tuple) -> float | None:
    """A number inside a row of report.json, or None when any level is missing."""
    value = row
    for key in keys:
        if isinstance(value, dict):
            value = value.get(key)
        elif isinstance(value, list | tuple) and isinstance(key, int) and key < len(value):
            value = value[key]
        else:
            return None
    return float(value) if isinstance(value, int | float) and math.isfinite(value) else None


def statistics(values: list[float]) -> dict:
    """{"mean", "std" (sample, None if n < 2), "n", "values"} of the runs' values."""
    if not values:
        return {"mean": None, "std": None, "n": 0, "values": []}
    array = np.asarray(values, np.float64)
    std = float(array.std(ddof=1)) if len(array) > 1 else None
    return {"mean": float(array.mean()), "std": std, "n": len(array), "values": list(values)}


def mean_std(stats: dict, digits: int = 1, sign: str = "") -> str:
    """The "mean ± std" of a `statistics` result, `digits` decimals (`sign` "+": signed mean); "—"
    without runs, "—" for the spread of one run."""
    if stats["mean"] is None:
        return "—"
    spread = "—" if stats["std"] is None else f"{stats['std']:.{digits}f}"
    return f"{stats['mean']:{sign}.{digits}f} ± {spread}"
