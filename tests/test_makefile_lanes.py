"""`make experiment EXPERIMENT_LANES=2`: each seed's rows as two make processes side by side,
pinned to disjoint halves of the cores. The lanes must never build the same stage (two writers of
one artifact), and together with the data they must build every training stage of the serial
plan. Checked on `make -n` plans, with a stand-in `taskset` that records its arguments."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from make_plans import dali_commands, make

pytestmark = pytest.mark.skipif(
    len(os.sched_getaffinity(0)) < 2, reason="lanes need two cores to split"
)


def dali_lines(*args: str) -> set[str]:
    return set(dali_commands(*args))


def lane_calls(tmp_path: Path, *variables: str) -> list[list[str]]:
    """The taskset calls of a planned 2-lane experiment: [[cores, make, goals..., VAR=...], ...]."""
    bin_dir, log = tmp_path / "bin", tmp_path / "taskset.log"
    bin_dir.mkdir()
    (bin_dir / "taskset").write_text(f'#!/bin/bash\necho "$*" >> {log}\nshift 2\nexec "$@"\n')
    (bin_dir / "taskset").chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}"}
    run = make(
        "-n", "experiment", "EXPERIMENT_LANES=2", f"EXPERIMENT_PREFIX={tmp_path}/exp", *variables,
        env=env,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    return [line.split() for line in log.read_text().splitlines()]


@pytest.mark.parametrize("sensor", ["waymo", "nuscenes"])
def test_lanes_build_disjoint_stages_and_every_training_row(tmp_path, sensor):
    calls = lane_calls(tmp_path, "SEEDS=0 1", f"SOURCE_SENSOR={sensor}")
    assert len(calls) == 4  # two lanes per seed
    for seed in ("0", "1"):
        lanes = [c for c in calls if f"SEED={seed}" in c]
        variables = [a for a in lanes[0] if "=" in a]
        lane_goals = [[a for a in c[3:] if "=" not in a and not a.startswith("-")] for c in lanes]
        data = dali_lines("data", *variables)
        plans = [dali_lines(*goals, *variables) - data for goals in lane_goals]
        assert all(plans) and not plans[0] & plans[1]  # no stage in both lanes
        goals = "iter2 x1-long controls cross-domain compare".split()
        goals += ["iter2-st"] if sensor == "nuscenes" else []
        goals += ["baselines"] if seed == "0" else []
        serial = dali_lines(*goals, *variables)
        training = {line for line in serial if any(f"dali {s} " in line for s in
                                                   ("pretrain", "retrain", "self-train"))}  # fmt: skip
        assert training and training <= plans[0] | plans[1]


def test_lanes_are_pinned_to_disjoint_halves_of_the_cores(tmp_path):
    calls = lane_calls(tmp_path, "SEEDS=0")
    cores = []
    for call in calls:
        assert call[0] == "-c"
        first, last = (int(c) for c in call[1].split("-"))
        cores.append(set(range(first, last + 1)))
    n = len(os.sched_getaffinity(0))
    assert len(cores) == 2 and not cores[0] & cores[1] and cores[0] | cores[1] == set(range(n))


def test_a_bad_lane_count_stops_before_anything_runs(tmp_path):
    run = make("experiment", "EXPERIMENT_LANES=3", f"EXPERIMENT_PREFIX={tmp_path}/exp")
    assert run.returncode != 0 and "EXPERIMENT_LANES must be 1 or 2" in run.stderr
    assert not (tmp_path / "exp-s0").exists()
