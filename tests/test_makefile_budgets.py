"""The Makefile's training budgets (`make -n`, nothing runs): per-iteration retraining epochs
(RETRAIN_EPOCHS_1/2; by default a quarter of 2 x RETRAIN_EPOCHS, then the rest) reach the
retrain commands, and the equal-budget controls count exactly the
frames DALI's x1 and x2 saw, whatever the split."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")


def plan(tmp_path: Path, goal: str, *variables: str) -> str:
    """The commands `make -n GOAL` would run for a fresh RUN."""
    result = subprocess.run(
        ["make", "--no-print-directory", "-n", "-C", str(REPO), goal, f"RUN={tmp_path / 'run'}",
         "EPOCHS=6", *variables],
        capture_output=True, text=True, timeout=60, check=True,
    )  # fmt: skip
    return result.stdout


def epochs(line: str) -> int:
    """The --epochs of a command line; shell arithmetic $(( ... )) evaluated."""
    value = re.search(r"--epochs (\$\(\(.*?\)\)|\d+)", line).group(1)
    if value.startswith("$(("):
        expression = value[3:-2]
        assert re.fullmatch(r"[\d\s+*()]+", expression), expression
        return int(eval(expression))  # digits, +, *, parentheses only
    return int(value)


def retrain_epochs(text: str) -> dict[str, int]:
    """--epochs of each retrain command, by the model it writes."""
    found = {}
    for line in text.splitlines():
        if " retrain " in line:
            found[re.search(r"--out \S*/(iter\d)/model", line).group(1)] = epochs(line)
    return found


def control_epochs(tmp_path: Path, name: str, *variables: str) -> int:
    goal = f"{tmp_path / 'run'}/baselines/{name}/model/manifest.json"
    lines = [line for line in plan(tmp_path, goal, *variables).splitlines() if " pretrain " in line]
    return epochs(lines[-1])


@pytest.mark.parametrize(
    ("variables", "expected"),
    [
        ((), {"iter1": 3, "iter2": 9}),  # RETRAIN_EPOCHS = EPOCHS = 6: a quarter, then the rest
        (("RETRAIN_EPOCHS=1",), {"iter1": 1, "iter2": 1}),  # at least one epoch each
        (("RETRAIN_EPOCHS=5",), {"iter1": 2, "iter2": 8}),
        (("RETRAIN_EPOCHS_1=6", "RETRAIN_EPOCHS_2=6"), {"iter1": 6, "iter2": 6}),  # the paper's
        (("RETRAIN_EPOCHS_1=2",), {"iter1": 2, "iter2": 10}),  # iteration 2 takes the rest
        (("RETRAIN_EPOCHS=4", "RETRAIN_EPOCHS_2=8"), {"iter1": 2, "iter2": 8}),
    ],
)
def test_per_iteration_budgets_and_equal_budget_controls(tmp_path, variables, expected):
    assert retrain_epochs(plan(tmp_path, "iter2", *variables)) == expected
    # each retraining epoch is source + PPCG frames (1:1): twice a pretraining epoch
    x1 = 6 + 2 * expected["iter1"]
    x2 = x1 + 2 * expected["iter2"]
    assert control_epochs(tmp_path, "source_x1_budget", *variables) == x1
    assert control_epochs(tmp_path, "source_x2_budget", *variables) == x2
    assert control_epochs(tmp_path, "oracle_x2_budget", *variables) == x2
    # x1 long: one retraining of iteration 1 and 2's epochs, from the source-only model
    long_plan = plan(tmp_path, f"{tmp_path / 'run'}/x1_long/model/manifest.json", *variables)
    [long_line] = [line for line in long_plan.splitlines() if "/x1_long/model" in line]
    assert " retrain " in long_line and "iter0/model" in long_line and "iter1/rc" in long_line
    assert 6 + 2 * epochs(long_line) == x2


def test_stage_flags_reach_every_pseudo_label_and_ppcg_command(tmp_path):
    text = plan(tmp_path, "iter2", "PSEUDO_FLAGS=--no-fit-points", "PPCG_FLAGS=--no-orient-models")
    lines = text.splitlines()
    pseudo = [line for line in lines if " pseudo-label " in line]
    ppcg = [line for line in lines if " ppcg-rc " in line or " ppcg-cf " in line]
    assert len(pseudo) == 2 and all("--no-fit-points" in line for line in pseudo)
    assert len(ppcg) == 4 and all("--no-orient-models" in line for line in ppcg)
    assert not any("--no-orient-models" in line for line in pseudo)


@pytest.mark.parametrize("value", ["0", "abc", "2.5"])
def test_a_retraining_budget_that_is_not_a_whole_number_of_epochs_stops_make(tmp_path, value):
    result = subprocess.run(
        ["make", "--no-print-directory", "-n", "-C", str(REPO), "iter2", f"RUN={tmp_path / 'run'}",
         f"RETRAIN_EPOCHS={value}"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert result.returncode != 0
    assert f"RETRAIN_EPOCHS must be a whole number of epochs >= 1, got '{value}'" in result.stderr
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("budget", ["source_x1_budget", "source_x2_budget"])
def test_each_control_gets_its_size_corrected_row(tmp_path, budget):
    """controls-x1 / controls-x2 also evaluate the control's own test-time PTSN predictions
    resized by its own sweep's factors (no second detector run), and the KITTI protocol covers
    that row."""
    goal = "controls-x1" if budget == "source_x1_budget" else "controls-x2"
    base = f"{tmp_path / 'run'}/baselines/{budget}"
    [line] = [x for x in plan(tmp_path, goal).splitlines() if "--size-correction" in x]
    assert f"--pred {base}/eval_ptsn/predictions.parquet" in line
    assert f"--scale-from {base}/ptsn --size-correction per-dim" in line
    assert line.rstrip().endswith(f"--out {base}/eval_ptsn_sized")
    rows = subprocess.run(["make", "--no-print-directory", "-C", str(REPO), "-p", "-n", "-q",
                           "kitti-protocol"], capture_output=True, text=True, timeout=60).stdout  # fmt: skip
    kitti_rows = next(x for x in rows.splitlines() if x.startswith("KITTI_ROWS"))
    assert f"baselines/{budget}/eval_ptsn_sized" in kitti_rows


@pytest.mark.parametrize(("sensor", "self_trains"), [("nuscenes", True), ("waymo", False)])
def test_the_nuscenes_experiment_self_trains_on_every_seed(tmp_path, sensor, self_trains):
    """`make experiment SOURCE_SENSOR=nuscenes` adds x2 + ST (the paper's ‡ belongs to that
    task) on every seed, not only the first; the Waymo-like task leaves it to EXPERIMENT_GOALS."""
    experiment = ("SEEDS=0 1", f"SOURCE_SENSOR={sensor}", f"EXPERIMENT_PREFIX={tmp_path / 'exp'}")
    text = plan(tmp_path, "experiment", *experiment)
    trained = {
        line.split("--out ")[1].split()[0] for line in text.splitlines() if " self-train " in line
    }
    expected = {f"{tmp_path / 'exp'}-s{seed}/iter2_st/model" for seed in (0, 1)}
    assert trained == (expected if self_trains else set())
    assert not (tmp_path / "exp-s0").exists()  # a plan: nothing ran


def test_compare_runs_on_both_recall_grids_with_every_main_row(tmp_path):
    """`make compare`: `dali compare` of the main rows against the x2-budget control, R40 and
    R400, seeded by SEED; `make experiment` runs it on every seed."""
    text = plan(tmp_path, "compare", "SEED=3").replace("\\\n", " ")
    lines = [line for line in text.splitlines() if " compare " in line and "--gt" in line]
    grids = sorted(re.search(r"--recall-positions (\d+)", line).group(1) for line in lines)
    assert grids == ["40", "400"]
    for line in lines:
        assert (
            "--pred control=" in line and "baselines/source_x2_budget/eval_ptsn/predictions" in line
        )
        for row in ("x2=", "x1-long=", "control-sized=", "oracle="):
            assert f"--pred {row}" in line
        assert "--seed 3" in line and "--front-only" in line
    experiment = ("SEEDS=0 1", f"EXPERIMENT_PREFIX={tmp_path / 'exp'}")
    text = plan(tmp_path, "experiment", *experiment).replace("\\\n", " ")
    written = {
        line.split("--out ")[1].split()[0]
        for line in text.splitlines()
        if " compare " in line and "--gt" in line
    }
    assert written == {
        f"{tmp_path / 'exp'}-s{seed}/compare_r{grid}.json" for seed in (0, 1) for grid in (40, 400)
    }
