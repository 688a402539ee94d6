"""Stage ppcg_cf: constraint-free pseudo point clouds of the target frames (body and outputs:
dali_cli.ppcg.run)."""

from __future__ import annotations

from pathlib import Path
from typing import Unpack

from dali_cli.ppcg.run import PpcgStageOptions, run_ppcg_stage
from dali_cli.runtime.errors import ParameterError
from dali_cli.store.manifest import StageOutcome


def ppcg_cf(
    target_dir: str | Path,
    boxes_dir: str | Path,
    library_dir: str | Path,
    out: str | Path,
    *,
    range_m: tuple[float, float] = (20.0, 50.0),
    **options: Unpack[PpcgStageOptions],
) -> StageOutcome:
    """CF pseudo point clouds (see dali_cli.ppcg.cf) of boxes moved to a centre range drawn
    from `range_m`; `options` as ppcg_rc's."""
    low, high = (float(v) for v in range_m)
    if not 0 < low <= high:
        raise ParameterError("range_m", f"need 0 < LOW <= HIGH, got {low}:{high}")
    method = {"range_m": (low, high)}
    return run_ppcg_stage(
        "cf", target_dir, boxes_dir, library_dir, out, method=method, options=options
    )
