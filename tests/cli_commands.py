"""The `dali` command tree for tests (a test helper): every leaf command by its full name and
the option words each accepts."""

from __future__ import annotations

import functools

import click

from dali_cli.cli import main as cli


@functools.cache
def cli_commands() -> dict[str, click.Command]:
    """Every leaf command of `dali`, by its full name ("import kitti"); built once."""
    ctx = click.Context(cli)
    found = {}

    def walk(group: click.Group, prefix: str) -> None:
        for name in group.list_commands(ctx):
            command = group.get_command(ctx, name)
            full = f"{prefix}{name}"
            if isinstance(command, click.Group):
                walk(command, full + " ")
            else:
                found[full] = command

    walk(cli, "")
    return found


def option_words(command: click.Command) -> set[str]:
    """Every word that names one of the command's options (aliases and --no- forms included)."""
    return {
        word
        for param in command.params
        if isinstance(param, click.Option)
        for word in param.opts + param.secondary_opts
    }
