"""Every dali command the Makefile would run names options its command has: a renamed or removed
option breaks `make demo`, `make experiment` or `make real-kitti` only when the stage is reached,
possibly hours into a run, so the plans are checked here against the CLI itself."""

from __future__ import annotations

import re
import shlex
import shutil

import click
import pytest

from dali_cli.cli import main as dali_main
from tests.make_plans import dali_commands

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")

GOALS = [
    ("demo",),
    ("experiment", "SEEDS=0 1", "EXPERIMENT_LANES=1"),
    ("experiment", "SEEDS=0", "SOURCE_SENSOR=nuscenes"),
    ("real-kitti", "REAL_DRIVE=/data/2011_09_26/2011_09_26_drive_0001_sync"),
    ("iter2-st", "x1-long", "baselines", "controls", "kitti-protocol", "cross-domain", "compare"),
    ("iter2", "DEVICE=cuda", "PRECISION=bf16"),
]


def dali_invocation(line: str) -> list[str]:
    """The words of the first dali command of one shell line, up to the next shell operator."""
    command = re.split(r";|&&|\|\||\s\|\s|\s2?>|\s&(?:\s|$)|\\$", line.split("bin/dali ", 1)[1])[0]
    return shlex.split(command)


def command_of(words: list[str]) -> tuple[click.Command, list[str]]:
    """The click command a word list names (groups descended) and the words after its name."""
    command: click.Command = dali_main
    while isinstance(command, click.Group) and words:
        sub = command.get_command(click.Context(command), words[0])
        if sub is None:
            break
        command, words = sub, words[1:]
    assert not isinstance(command, click.Group), f"no subcommand in {words}"
    return command, words


def option_names(command: click.Command) -> set[str]:
    names: set[str] = set()
    for param in command.params:
        if isinstance(param, click.Option):
            names.update(param.opts)
            names.update(param.secondary_opts)
    return names


@pytest.mark.parametrize("goal", GOALS, ids=lambda g: " ".join(g))
def test_every_planned_dali_option_exists(tmp_path, goal):
    lines = [line for line in dali_commands(*goal, f"RUN={tmp_path / 'run'}", f"REAL_RUN={tmp_path / 'real'}")
             if "bin/dali " in line]  # fmt: skip
    assert lines, goal
    for line in lines:
        command, words = command_of(dali_invocation(line))
        known = option_names(command)
        for word in words:
            if word.startswith("--"):
                assert word.split("=", 1)[0] in known, (
                    f"`make {' '.join(goal)}` runs {command.name} {word}: {line}"
                )


def test_a_removed_option_is_caught():
    command, words = command_of(dali_invocation(".venv/bin/dali eval --size-score-min 0.3 --out x"))
    assert command.name == "eval" and "--size-score-min" not in option_names(command)
    assert "--score-min" in option_names(command) and words[0] == "--size-score-min"
