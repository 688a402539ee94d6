"""Stage ppcg_cf: constraint-free pseudo point clouds of the target frames (body and outputs:
dali_cli.ppcg.run)."""

from __future__ import annotations

from pathlib import Path
from typing import Unpack

from dali_cli.ppcg.frame import DEFAULT_POINT_MARGIN_M
from dali_cli.ppcg.run import PpcgOptions, run_ppcg_stage
from dali_cli.runtime.errors import ParameterError
from dali_cli.store.manifest import StageOutcome
from dali_cli.world.cars import LABEL_SLACK_M


def ppcg_cf(
    target_dir: str | Path,
    boxes_dir: str | Path,
    library_dir: str | Path,
    out: str | Path,
    *,
    range_m: tuple[float, float] = (20.0, 50.0),
    top_k: int = 1,
    seed: int = 0,
    ground_margin_m: float = 0.1,
    orient_models: bool | None = None,
    point_margin_m: float = DEFAULT_POINT_MARGIN_M,
    label_slack_m: tuple[float, float, float] = tuple(LABEL_SLACK_M),
    **options: Unpack[PpcgOptions],
) -> StageOutcome:
    """CF pseudo point clouds (see dali_cli.ppcg.cf); `orient_models`, `point_margin_m`,
    `label_slack_m` and `options` as ppcg_rc's."""
    low, high = (float(v) for v in range_m)
    if not 0 < low <= high:
        raise ParameterError("range_m", f"need 0 < LOW <= HIGH, got {low}:{high}")
    shared = {"top_k": top_k, "seed": seed, "ground_margin_m": ground_margin_m}
    return run_ppcg_stage(
        "cf", target_dir, boxes_dir, library_dir, out,
        method={"range_m": (low, high)}, shared=shared,
        orient_models=orient_models, point_margin_m=point_margin_m, label_slack_m=label_slack_m,
        options=options,
    )  # fmt: skip
