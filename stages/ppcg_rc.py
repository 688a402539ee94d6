"""Stage ppcg_rc: ray-constrained pseudo point clouds of the target frames (body and outputs:
dali_cli.ppcg.run)."""

from __future__ import annotations

from pathlib import Path
from typing import Unpack

from dali_cli.ppcg.frame import DEFAULT_POINT_MARGIN_M
from dali_cli.ppcg.point_models import angular_threshold_rad
from dali_cli.ppcg.rc import RcParams
from dali_cli.ppcg.run import PpcgOptions, run_ppcg, target_profile
from dali_cli.runtime.device import check_options
from dali_cli.runtime.errors import ParameterError
from dali_cli.store.artifacts import FrameSet
from dali_cli.store.manifest import StageOutcome
from dali_cli.world.cars import LABEL_SLACK_M


def ppcg_rc(
    target_dir: str | Path,
    boxes_dir: str | Path,
    library_dir: str | Path,
    out: str | Path,
    *,
    max_points: int = 300,
    min_points: int = 3,
    top_k: int = 1,
    seed: int = 0,
    ground_margin_m: float = 0.1,
    orient_models: bool | None = None,
    point_margin_m: float = DEFAULT_POINT_MARGIN_M,
    label_slack_m: tuple[float, float, float] = tuple(LABEL_SLACK_M),
    **options: Unpack[PpcgOptions],
) -> StageOutcome:
    """RC pseudo point clouds (see dali_cli.ppcg.rc); `orient_models`: turn a box round when its
    model fits its points better that way (dali_cli.ppcg.orient; None, the default: with mesh
    models only); `point_margin_m`: a box's points are those in the box grown by this (m);
    `label_slack_m`: (l, w, h) room a box leaves around its car: the model fills the box
    shrunk by it (m; the synthetic world's labels by default);
    `options`: sensor, models, label, engine
    and stage switches (dali_cli.ppcg.run.PpcgOptions; `bank` replaces the library in tests)."""
    if min_points < 1 or max_points <= min_points:
        raise ParameterError(
            ("min_points", "max_points"), f"need 1 <= MIN < MAX, got {min_points}, {max_points}"
        )
    check_options(options, PpcgOptions, "ppcg_rc")
    _, profile = target_profile(
        FrameSet(target_dir), options.get("sensor"), options.get("sensors_path")
    )
    shared = {"top_k": top_k, "seed": seed, "ground_margin_m": ground_margin_m}
    # run_ppcg checks the margin, resolves the orientation (it knows the model kind) and
    # records each only when used
    params = RcParams(
        mount_height_m=profile.mount_height_m,
        theta_rad=angular_threshold_rad(profile.points_per_beam),
        max_points=max_points,
        min_points=min_points,
        orient=orient_models,
        point_margin_m=float(point_margin_m),
        label_slack_m=tuple(float(v) for v in label_slack_m),
        **shared,
    )
    stage_params = {"max_points": max_points, "min_points": min_points, **shared}
    return run_ppcg(
        "rc", target_dir, boxes_dir, library_dir, out,
        params=params, stage_params=stage_params, **options,
    )  # fmt: skip
