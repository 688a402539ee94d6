"""Stage ppcg_rc: ray-constrained pseudo point clouds of the target frames (body and outputs:
dali_cli.ppcg.run)."""

from __future__ import annotations

from pathlib import Path
from typing import Unpack

from dali_cli.ppcg.frame import DEFAULT_POINT_MARGIN_M
from dali_cli.ppcg.run import PpcgOptions, run_ppcg_stage
from dali_cli.runtime.errors import ParameterError
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
    shared = {"top_k": top_k, "seed": seed, "ground_margin_m": ground_margin_m}
    return run_ppcg_stage(
        "rc", target_dir, boxes_dir, library_dir, out,
        method={"max_points": max_points, "min_points": min_points}, shared=shared,
        orient_models=orient_models, point_margin_m=point_margin_m, label_slack_m=label_slack_m,
        options=options,
    )  # fmt: skip
