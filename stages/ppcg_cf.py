"""Stage ppcg_cf: constraint-free pseudo point clouds of the target frames (body and outputs:
dali_cli.ppcg.run)."""

from __future__ import annotations

from pathlib import Path
from typing import Unpack

from dali_cli.ppcg.cf import CfParams
from dali_cli.ppcg.frame import DEFAULT_POINT_MARGIN_M
from dali_cli.ppcg.point_models import angular_threshold_rad
from dali_cli.ppcg.run import PpcgOptions, run_ppcg, target_profile
from dali_cli.runtime.device import check_options
from dali_cli.runtime.errors import ParameterError
from dali_cli.store.artifacts import FrameSet
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
    check_options(options, PpcgOptions, "ppcg_cf")
    _, profile = target_profile(
        FrameSet(target_dir), options.get("sensor"), options.get("sensors_path")
    )
    shared = {"top_k": top_k, "seed": seed, "ground_margin_m": ground_margin_m}
    # run_ppcg checks the margin, resolves the orientation (it knows the model kind) and
    # records each only when used
    params = CfParams(
        theta_rad=angular_threshold_rad(profile.points_per_beam),
        range_m=(low, high),
        orient=orient_models,
        point_margin_m=float(point_margin_m),
        label_slack_m=tuple(float(v) for v in label_slack_m),
        **shared,
    )
    stage_params = {"range_m": [low, high], **shared}
    return run_ppcg(
        "cf", target_dir, boxes_dir, library_dir, out,
        params=params, stage_params=stage_params, **options,
    )  # fmt: skip
