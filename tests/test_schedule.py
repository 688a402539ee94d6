"""One learning-rate schedule across pretraining and retraining: `dali pretrain --schedule-epochs`
trains the first part of a one-cycle schedule and records where it stopped in the model card;
`dali retrain --continue-schedule` runs the rest instead of warming up again (docs/RESULTS.md,
session 23: a restarted schedule loses the steps before it)."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner
from test_retrain import write_toy_world

from dali_cli.cli import main
from dali_cli.detector import TrainSettings
from dali_cli.detector.train import one_cycle, schedule_lr
from dali_cli.store.manifest import read_manifest
from dali_cli.store.model_card import ModelCard


def lrs(steps: int, settings: TrainSettings) -> np.ndarray:
    """The learning rate of each of a run's `steps` steps (the training loop's fractions)."""
    return np.array([schedule_lr(step / steps, settings) for step in range(steps)])


def test_two_parts_of_a_schedule_are_the_whole_schedule():
    whole = lrs(12, TrainSettings(lr=5e-3))
    first = lrs(4, TrainSettings(lr=5e-3, schedule=(0.0, 4 / 12)))
    rest = lrs(8, TrainSettings(lr=5e-3, schedule=(4 / 12, 1.0)))
    assert np.allclose(np.concatenate([first, rest]), whole, rtol=1e-12, atol=0)
    # a restarted schedule warms up from lr / 10 again; the continued one goes on near the peak
    restarted = lrs(8, TrainSettings(lr=5e-3))
    assert restarted[0] == pytest.approx(5e-4) and rest[0] > 0.95 * 5e-3
    assert schedule_lr(0.0, TrainSettings()) == one_cycle(0.0, 5e-3, 0.3)


def test_model_card_reads_and_clears_the_schedule_stop():
    card = ModelCard(stage="pretrain", schedule_stop=0.25)
    assert ModelCard.from_meta({"card": card.to_dict()}).schedule_stop == 0.25
    assert card.carried_forward("retrain").schedule_stop is None  # a retrain runs to the end
    for bad in (1.0, 0, -0.5, "0.5", True, None):
        assert ModelCard.from_meta({"card": {"schedule_stop": bad}}).schedule_stop is None
    assert ModelCard.from_meta({"provenance": {}}).schedule_stop is None  # older checkpoints


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    return write_toy_world(tmp_path_factory.mktemp("schedule"), "rc")


def pretrain(world, out, *extra):
    return CliRunner().invoke(
        main,
        ["pretrain", "--source", str(world / "source"), "--out", str(out), "--epochs", "1",
         "--detector-config", str(world / "config.json"), "--quiet", *extra],
    )  # fmt: skip


def retrain(world, init, out, *extra):
    return CliRunner().invoke(
        main,
        ["retrain", "--init", str(init), "--source", str(world / "source"), "--ppcg",
         str(world / "rc"), "--out", str(out), "--epochs", "1", "--quiet", *extra],
    )  # fmt: skip


def logged_lr(model_dir) -> dict[int, float]:
    log = pq.read_table(model_dir / "train_log.parquet").to_pydict()
    return dict(zip(log["step"], log["lr"], strict=True))


def test_pretrain_part_then_retrain_continues_the_schedule(world):
    part = world / "part"
    result = pretrain(world, part, "--schedule-epochs", "3")
    assert result.exit_code == 0, result.output
    card = json.loads((part / "model.json").read_text())["card"]
    assert card["schedule_stop"] == pytest.approx(1 / 3)
    assert read_manifest(part)["params"]["schedule"] == pytest.approx([0.0, 1 / 3])
    steps = read_manifest(part)["outputs"]["counts"]["steps"]  # 3 frames: 3 steps
    lr = logged_lr(part)
    assert lr[steps] == pytest.approx(one_cycle((steps - 1) / (3 * steps), 5e-3, 0.3))

    continued = world / "continued"
    result = retrain(world, part, continued, "--continue-schedule")
    assert result.exit_code == 0, result.output
    assert read_manifest(continued)["params"]["schedule"] == pytest.approx([1 / 3, 1.0])
    assert json.loads((continued / "model.json").read_text())["card"]["schedule_stop"] is None
    first = logged_lr(continued)[1]
    assert first == pytest.approx(one_cycle(1 / 3, 5e-3, 0.3)) and first > 0.95 * 5e-3
    restarted = world / "restarted"
    assert retrain(world, part, restarted).exit_code == 0
    assert logged_lr(restarted)[1] == pytest.approx(5e-4)  # a fresh schedule warms up again
    assert "schedule" not in read_manifest(restarted)["params"]  # the default adds no parameter


def test_schedule_errors_write_nothing(world, tmp_path):
    whole = world / "whole"
    assert pretrain(world, whole).exit_code == 0
    assert "schedule_stop" in json.loads((whole / "model.json").read_text())["card"]
    result = retrain(world, whole, tmp_path / "a", "--continue-schedule")
    assert result.exit_code == 2 and "nothing to continue" in result.output
    assert str(whole) in result.output and "--schedule-epochs" in result.output.replace("\n", " ")
    part = world / "part-for-errors"
    assert pretrain(world, part, "--schedule-epochs", "2").exit_code == 0
    result = retrain(world, part, tmp_path / "b", "--continue-schedule", "--init-from", "scratch")
    assert result.exit_code == 2 and "--init-from previous" in result.output
    result = pretrain(world, tmp_path / "c", "--schedule-epochs", "0.5")
    assert result.exit_code == 2 and "fewer than" in result.output
    result = pretrain(world, tmp_path / "d", "--schedule-epochs", "2", "--minutes", "1")
    assert result.exit_code == 2 and "--minutes" in result.output
    assert not any((tmp_path / name).exists() for name in "abcd")
