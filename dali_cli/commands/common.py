"""Options and helpers shared by the stage commands."""

from __future__ import annotations

import click

from dali_cli.manifest import StageOutcome


def stage_options(function):
    """--force and --dry-run, the two switches every stage command has."""
    function = click.option(
        "--dry-run", is_flag=True, help="Print whether the stage would run, and why; write nothing."
    )(function)
    function = click.option(
        "--force", is_flag=True, help="Rerun even when the output is up to date."
    )(function)
    return function


def sensors_option(function):
    return click.option(
        "--sensors",
        "sensors_path",
        type=click.Path(exists=True, dir_okay=False),
        default=None,
        help="sensors.toml to use instead of the project's.",
    )(function)


def not_implemented(name: str, issue: str) -> click.Command:
    """A placeholder command: exits 1 and says what is missing. No fake output."""

    @click.command(
        name=name,
        context_settings={"ignore_unknown_options": True, "allow_extra_args": True},
        help=f"Not implemented yet ({issue}).",
    )
    def placeholder() -> None:
        click.echo(f"dali {name}: not implemented yet ({issue})", err=True)
        raise SystemExit(1)

    return placeholder


def report_outcome(outcome: StageOutcome) -> None:
    """Exit code 0 for ran/skipped/dry-run; the stage has already printed what it did."""
    del outcome
