"""Every dali command the Makefile would run names options its command has: a renamed or removed
option breaks `make demo`, `make experiment` or `make real-kitti` only when the stage is reached,
possibly hours into a run, so the plans are checked here against the CLI itself."""

from __future__ import annotations

import re
import shlex
import shutil

import pytest
from cli_commands import cli_commands, option_words
from make_plans import dali_commands

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")

GOALS = [
    ("demo",),
    ("experiment", "SEEDS=0 1", "EXPERIMENT_LANES=1"),
    ("experiment", "SEEDS=0", "SOURCE_SENSOR=nuscenes"),
    ("real-kitti", "REAL_DRIVE=/data/2011_09_26/2011_09_26_drive_0001_sync"),
    (
        "real-kitti",
        "SEEDS=0 1",
        "REAL_DRIVES=/data/2011_09_26/2011_09_26_drive_0005_sync /data/sequences/04",
    ),
    ("iter2-st", "x1-long", "baselines", "controls", "kitti-protocol", "cross-domain", "compare"),
    ("iter2", "DEVICE=cuda", "PRECISION=bf16"),
]


def dali_invocation(line: str) -> list[str]:
    """The words of the first dali command of one shell line, up to the next shell operator."""
    command = re.split(r";|&&|\|\||\s\|\s|\s2?>|\s&(?:\s|$)|\\$", line.split("bin/dali ", 1)[1])[0]
    return shlex.split(command)


def command_of(words: list[str]) -> tuple[str, list[str]]:
    """The full name of the dali command a word list starts with and the words after it."""
    commands = cli_commands()
    for count in (2, 1):
        name = " ".join(words[:count])
        if name in commands:
            return name, words[count:]
    raise AssertionError(f"no dali command in {words}")


@pytest.mark.parametrize("goal", GOALS, ids=lambda g: " ".join(g))
def test_every_planned_dali_option_exists(tmp_path, goal):
    lines = [line for line in dali_commands(*goal, f"RUN={tmp_path / 'run'}", f"REAL_RUN={tmp_path / 'real'}")
             if "bin/dali " in line]  # fmt: skip
    assert lines, goal
    for line in lines:
        name, words = command_of(dali_invocation(line))
        known = option_words(cli_commands()[name])
        for word in words:
            if word.startswith("--"):
                assert word.split("=", 1)[0] in known, (
                    f"`make {' '.join(goal)}` runs {name} {word}: {line}"
                )


def test_a_removed_option_is_caught():
    name, words = command_of(dali_invocation(".venv/bin/dali eval --score-min 0.3 --out x"))
    known = option_words(cli_commands()[name])
    assert name == "eval" and "--score-min" not in known  # eval's cut is --size-score-min
    assert "--size-score-min" in known and words[0] == "--score-min"
