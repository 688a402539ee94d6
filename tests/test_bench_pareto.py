"""The Pareto benchmark's fronts still run against the package's current interfaces.

A benchmark is not a timed test, but its code calls the library (PTSN's search, the detector,
ray casting) and nothing else exercises those calls: a refactor of the library
can break a front silently. These run each front on a few tiny inputs (an untrained small
detector, toy scenes) and check properties of what comes back, not timings.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from toy_scenes import SMALL_NET

from dali_cli.cli import main
from dali_cli.detector import DetectorConfig, PillarCenterNet, save_checkpoint

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))

from pareto import detector_front, pillar_front, ptsn_front, raycast_front  # noqa: E402
from pareto.plots import non_dominated  # noqa: E402


@pytest.fixture(scope="module")
def tiny_model_and_frames(tmp_path_factory):
    """An untrained small detector saved as a checkpoint, and 2 synthetic KITTI-like frames
    (with KITTI's label columns, which the front's KITTI-protocol AP needs)."""
    root = tmp_path_factory.mktemp("pareto")
    synth = ["synth", "--sensor", "kitti", "--cars", "kitti", "--frames", "2", "--seed", "4"]
    result = CliRunner().invoke(main, [*synth, "--workers", "1", "--out", str(root / "target")])
    assert result.exit_code == 0, result.output
    torch.manual_seed(0)
    net = PillarCenterNet(DetectorConfig(**SMALL_NET))
    (root / "model").mkdir()
    save_checkpoint(root / "model", net, {"provenance": {"stage": "test"}})
    return root / "model", root / "target"


def test_raycast_front_default_is_the_accurate_robust_float64_point():
    result = raycast_front.measure(repeats=1, boxes=6)
    points = result["points"] if isinstance(result, dict) else result
    defaults = [p for p in points if p["default"]]
    assert len(defaults) == 1 and defaults[0]["robust"] and defaults[0]["setup"] == "float64"
    assert defaults[0]["error_mm_p999_all_rays"] < 0.1  # the stated bound of the default path
    assert all(p["rays_per_cpu_second"] > 0 for p in points)


@pytest.mark.slow  # a whole PTSN front
def test_ptsn_front_runs_and_its_reference_has_no_error(tiny_model_and_frames):
    model, target = tiny_model_and_frames
    result = ptsn_front.measure(model, target, "kitti", quick=True, frames=2)
    points = result["points"]
    assert points[0]["search"] == "grid" and points[0]["scale_error"] == 0.0
    assert sum(p["default"] for p in points) == 1
    assert all(p["frame_passes"] > 0 and p["scale_error"] >= 0 for p in points)
    # the reference grid costs the most passes: every other search asks for fewer
    assert max(p["frame_passes"] for p in points) == points[0]["frame_passes"]


def test_detector_front_times_every_variant_and_scores_it(tiny_model_and_frames):
    model, target = tiny_model_and_frames
    result = detector_front.measure(model, target, "kitti", quick=True, frames=2, repeats=2)
    assert result["repeats"] == 2
    for point in result["points"]:
        assert "error" not in point, point.get("error")
        assert len(point["seconds_per_frame_runs"]) == 2
        assert point["seconds_per_frame"] == pytest.approx(
            np.median(point["seconds_per_frame_runs"]), abs=1e-4
        )
        assert point["ap3d_07_all"] is None or 0.0 <= point["ap3d_07_all"] <= 100.0


def test_pillar_front_seed_means_average_each_configuration():
    points = [
        {"pillar_m": 0.32, "budget": "equal frames", "frames_seen": 480, "default": True,
         "train_seconds": 90.0, "ap_loss": 50.0},
        {"pillar_m": 0.32, "budget": "equal frames", "frames_seen": 480, "default": True,
         "train_seconds": 92.0, "ap_loss": 48.0},
        {"pillar_m": 0.24, "budget": "equal frames", "frames_seen": 480, "default": False,
         "train_seconds": 120.0, "ap_loss": 38.0},
        {"pillar_m": 0.32, "budget": "equal time", "frames_seen": 624, "default": False,
         "train_seconds": 119.0, "ap_loss": 39.0},
    ]  # fmt: skip
    means = {(p["pillar_m"], p["budget"]): p for p in pillar_front.seed_means(points)}
    assert set(means) == {(0.32, "equal frames"), (0.24, "equal frames"), (0.32, "equal time")}
    default = means[(0.32, "equal frames")]
    assert default["seeds"] == 2 and default["default"]
    assert default["train_seconds"] == 91.0 and default["ap_loss"] == 49.0
    assert not means[(0.32, "equal time")]["default"]


def test_non_dominated_keeps_exactly_the_front():
    points = [(1.0, 5.0), (2.0, 3.0), (3.0, 3.0), (4.0, 1.0), (2.5, 4.0), (1.0, 5.0)]
    front = non_dominated(points)
    # (3, 3) is beaten by (2, 3), (2.5, 4) by (2, 3); the duplicated (1, 5) beats neither copy
    assert sorted(front) == [0, 1, 3, 5]
