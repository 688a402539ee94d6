"""docs/INTERFACES.md's stage table matches the CLI: every command that writes an artifact has a
row, its stage function exists, and the options the row names are exactly the command's options
(besides the shared ones the document lists), so the table cannot drift from the code."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import click
import pytest
from cli_commands import cli_commands

from dali_cli.commands.common import AliasedOption

DOC = Path(__file__).resolve().parents[1] / "docs" / "INTERFACES.md"
OPTION = re.compile(r"`(--[a-z0-9][a-z0-9-]*)`")
COMMAND = re.compile(r"`dali ([a-z0-9 -]+)`")


def section(text: str, heading: str) -> str:
    """The body of the markdown section `heading` (up to the next heading of its level or above)."""
    start = text.index(heading)
    level = heading.split(" ")[0]
    rest = text[start + len(heading) :]
    ends = [m.start() for m in re.finditer(rf"^#{{1,{len(level)}}} ", rest, re.MULTILINE)]
    return rest[: ends[0]] if ends else rest


def parse_stage_table() -> tuple[dict[str, dict], set[str], set[str]]:
    """(rows by command, the shared options, the read-only commands) of the stage table."""
    body = section(DOC.read_text(encoding="utf-8"), "### Stage table")
    shared_line = next(line for line in body.split("\n\n") if "Every stage command also" in line)
    readers_line = next(line for line in body.split("\n\n") if "only read or draw" in line)
    rows = {}
    for line in body.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) != 5 or not cells[0].startswith("`dali "):
            continue
        command = COMMAND.fullmatch(cells[0]).group(1)
        rows[command] = {
            "function": cells[1].strip("`"),
            "inputs": set(OPTION.findall(cells[2])),
            "parameters": set(OPTION.findall(cells[4])),
        }
    return rows, set(OPTION.findall(shared_line)), set(COMMAND.findall(readers_line))


def options_of(command: click.Command) -> set[str]:
    """The command's option names as a user types them (the long primary name of each; a renamed
    option's current name, not the former ones it still answers to)."""
    return {
        param.opts[0] if isinstance(param, AliasedOption) else max(param.opts, key=len)
        for param in command.params
        if isinstance(param, click.Option)
    }


ROWS, SHARED, READERS = parse_stage_table()
COMMANDS = cli_commands()


def test_every_command_is_in_the_table_or_a_reader():
    assert len(ROWS) >= 15, "the stage table was not found or lost its rows"
    assert set(COMMANDS) == set(ROWS) | READERS, (
        f"not documented: {sorted(set(COMMANDS) - set(ROWS) - READERS)}; "
        f"documented but not a command: {sorted((set(ROWS) | READERS) - set(COMMANDS))}"
    )
    assert not set(ROWS) & READERS


@pytest.mark.parametrize("command", sorted(ROWS))
def test_stage_function_exists(command):
    module, _, name = ROWS[command]["function"].rpartition(".")
    assert module.startswith("stages.")
    assert callable(getattr(importlib.import_module(module), name, None)), ROWS[command]


@pytest.mark.parametrize("command", sorted(ROWS))
def test_row_names_exactly_the_commands_options(command):
    row = ROWS[command]
    documented = row["inputs"] | row["parameters"]
    actual = options_of(COMMANDS[command])
    assert not row["inputs"] & row["parameters"], f"{command}: an option in both columns"
    missing = actual - documented - SHARED
    unknown = documented - actual
    assert not missing, f"dali {command}: options not in docs/INTERFACES.md: {sorted(missing)}"
    assert not unknown, f"dali {command}: documented options it lacks: {sorted(unknown)}"


def test_shared_options_exist():
    every = set().union(*(options_of(c) for c in COMMANDS.values()))
    assert SHARED and SHARED <= every, sorted(SHARED - every)
