"""Stage ppcg_rc: ray-constrained pseudo point clouds of the target frames (body and outputs:
dali_cli.ppcg.run)."""

from __future__ import annotations

from pathlib import Path
from typing import Unpack

from dali_cli.ppcg.run import PpcgStageOptions, run_ppcg_stage
from dali_cli.runtime.errors import ParameterError
from dali_cli.store.manifest import StageOutcome


def ppcg_rc(
    target_dir: str | Path,
    boxes_dir: str | Path,
    library_dir: str | Path,
    out: str | Path,
    *,
    max_points: int = 300,
    min_points: int = 3,
    **options: Unpack[PpcgStageOptions],
) -> StageOutcome:
    """RC pseudo point clouds (see dali_cli.ppcg.rc) of the boxes with MIN <= points < MAX;
    `options`: the settings ppcg-cf shares (top_k, seed, ground_margin_m, orient_models,
    point_margin_m, label_slack_m), sensor, models, label, engine and stage switches
    (dali_cli.ppcg.run.PpcgStageOptions; `bank` replaces the library in tests)."""
    if min_points < 1 or max_points <= min_points:
        raise ParameterError(
            ("min_points", "max_points"), f"need 1 <= MIN < MAX, got {min_points}, {max_points}"
        )
    method = {"max_points": max_points, "min_points": min_points}
    return run_ppcg_stage(
        "rc", target_dir, boxes_dir, library_dir, out, method=method, options=options
    )
