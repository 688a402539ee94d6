"""Stage ppcg_rc: ray-constrained pseudo point clouds of the target frames (body and outputs:
dali_cli.ppcg.run)."""

from __future__ import annotations

from pathlib import Path

from dali_cli.artifacts import FrameSet
from dali_cli.errors import ParameterError
from dali_cli.manifest import StageOutcome
from dali_cli.ppcg.models import ModelBank
from dali_cli.ppcg.point_models import angular_threshold_rad
from dali_cli.ppcg.rc import RcParams
from dali_cli.ppcg.run import run_ppcg, target_profile


def ppcg_rc(
    target_dir: str | Path,
    boxes_dir: str | Path,
    library_dir: str | Path,
    out: str | Path,
    *,
    sensor: str | None = None,
    sensors_path: str | None = None,
    models: str | None = None,
    max_points: int = 300,
    min_points: int = 3,
    top_k: int = 1,
    seed: int = 0,
    ground_margin_m: float = 0.1,
    label: str | None = "Car",
    workers: int | None = 1,
    force: bool = False,
    dry_run: bool = False,
    progress: bool = True,
    bank: ModelBank | None = None,
    executor: str = "local",
    ray_address: str | None = None,
) -> StageOutcome:
    """RC pseudo point clouds (see dali_cli.ppcg.rc); `bank` replaces the library (tests)."""
    if min_points < 1 or max_points <= min_points:
        raise ParameterError(
            ("min_points", "max_points"), f"need 1 <= MIN < MAX, got {min_points}, {max_points}"
        )
    _, profile = target_profile(FrameSet(target_dir), sensor, sensors_path)
    params = RcParams(
        mount_height_m=profile.mount_height_m,
        theta_rad=angular_threshold_rad(profile.points_per_beam),
        max_points=max_points,
        min_points=min_points,
        top_k=top_k,
        seed=seed,
        ground_margin_m=ground_margin_m,
    )
    stage_params = {
        "max_points": max_points,
        "min_points": min_points,
        "top_k": top_k,
        "seed": seed,
        "ground_margin_m": ground_margin_m,
    }
    return run_ppcg(
        "rc", target_dir, boxes_dir, library_dir, out,
        params=params, stage_params=stage_params, sensor=sensor, sensors_path=sensors_path,
        models=models, label=label, workers=workers, force=force, dry_run=dry_run,
        progress=progress, bank=bank, executor=executor, ray_address=ray_address,
    )  # fmt: skip
