"""bf16 autocast (`--precision bf16`, `make PRECISION=bf16`): the networks' matrix products run in
bf16 in training and inference, the second stage's included, while losses, maps and boxes stay
float32 / float64; fp32 (the default) runs none of them in bf16."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from make_plans import dali_commands
from toy_scenes import place_cars, scan

from dali_cli.detector import Detector, DetectorConfig, PillarCenterNet, TrainSettings
from dali_cli.detector.data import Sample
from dali_cli.detector.train import optimize_step
from dali_cli.sensors import get_profile

MODEL_STAGES = ("pretrain", "retrain", "self-train", "ptsn-sweep", "pseudo-label", "eval")


def toy_frame(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A KITTI-like toy scan with five box cars: points (n, 4) and boxes (5, 7), ground frame."""
    kitti = get_profile("kitti")
    rng = np.random.default_rng(seed)
    cars = place_cars(rng, 5, kitti.car_mean_lwh_m, kitti.mount_height_m, (6.0, 30.0), (-8.0, 8.0))
    points = scan(cars, kitti, beams=32, points_per_beam=600, azimuth_range_deg=(-45.0, 45.0))
    points[:, 2] += kitti.mount_height_m
    cars[:, 2] += kitti.mount_height_m
    return points.astype(np.float32), cars


def dtypes_seen(net: PillarCenterNet) -> dict[str, list[torch.dtype]]:
    """Record the output dtypes of a backbone conv, the refiner's first point layer and the
    refiner itself on every call."""
    seen: dict[str, list[torch.dtype]] = {"conv": [], "refiner_linear": [], "refiner_out": []}
    net.backbone.blocks[0][0][0].register_forward_hook(
        lambda _m, _i, out: seen["conv"].append(out.dtype)
    )
    net.refiner.point_mlp[0].register_forward_hook(
        lambda _m, _i, out: seen["refiner_linear"].append(out.dtype)
    )
    net.refiner.register_forward_hook(
        lambda _m, _i, out: seen["refiner_out"].extend(t.dtype for t in out)
    )
    return seen


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_training_step_runs_both_stages_at_the_precision(precision):
    torch.manual_seed(0)
    net = PillarCenterNet(DetectorConfig())
    net.train()
    seen = dtypes_seen(net)
    optimizer = torch.optim.AdamW(net.parameters(), lr=1e-3)
    settings = TrainSettings(epochs=1, batch_size=1, threads=1, precision=precision)
    sample = Sample(*toy_frame(0))
    terms = optimize_step(net, net, optimizer, [sample], settings, torch.device("cpu"), 0, [0])
    expected = torch.bfloat16 if precision == "bf16" else torch.float32
    assert seen["conv"] == [expected]
    assert seen["refiner_linear"] and set(seen["refiner_linear"]) == {expected}
    assert set(seen["refiner_out"]) == {torch.float32}  # the refine losses are float32
    assert all(torch.isfinite(value) and value.dtype == torch.float32 for value in terms.values())
    grads = [p.grad for p in net.refiner.parameters()]
    assert all(
        g is not None and g.dtype == torch.float32 and torch.isfinite(g).all() for g in grads
    )
    assert any(g.abs().sum() > 0 for g in grads)


def test_bf16_inference_refines_in_bf16_and_returns_float_boxes():
    torch.manual_seed(0)
    net = PillarCenterNet(DetectorConfig(score_threshold=0.0))  # untrained: keep every top-k box
    seen = dtypes_seen(net)
    points, _ = toy_frame(1)
    points[:, 2] -= get_profile("kitti").mount_height_m  # predict() takes sensor-frame points
    ((boxes32, scores32),) = Detector(net, precision="fp32").predict([points])
    assert set(seen["refiner_linear"]) == {torch.float32}
    for values in seen.values():
        values.clear()
    ((boxes, scores),) = Detector(net, precision="bf16").predict([points])
    assert seen["conv"] == [torch.bfloat16]
    assert seen["refiner_linear"] and set(seen["refiner_linear"]) == {torch.bfloat16}
    assert boxes.dtype == np.float64 and scores.dtype == np.float32 and len(boxes) > 0
    assert np.isfinite(boxes).all() and np.isfinite(scores).all()
    assert len(boxes32) > 0


def make_plan(tmp_path: Path, *variables: str) -> list[str]:
    """The dali commands `make -n` would run for x2, x1 long, the controls and the baselines."""
    goals = ("iter2", "x1-long", "controls", "baselines", "iter2-st")
    return dali_commands(*goals, f"RUN={tmp_path / 'run'}", *variables)


def model_stage(line: str) -> str | None:
    """The detector stage a planned command runs (an eval of saved predictions runs none)."""
    for stage in MODEL_STAGES:
        if f"dali {stage} " in line and (stage != "eval" or "--model " in line):
            return stage
    return None


def test_make_precision_reaches_every_model_stage_and_nothing_else(tmp_path):
    plan = make_plan(tmp_path, "PRECISION=bf16")
    model = [line for line in plan if model_stage(line)]
    assert {model_stage(line) for line in model} == set(MODEL_STAGES)
    assert all("--precision bf16" in line for line in model)
    assert all("--precision" not in line for line in plan if line not in model)
    assert all("--precision" not in line for line in make_plan(tmp_path))
