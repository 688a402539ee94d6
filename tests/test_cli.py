"""The `dali` command group: version, help, every command registered and importable."""

from __future__ import annotations

import os
import re
import subprocess
import sys

from click.testing import CliRunner

from dali_cli import __version__
from dali_cli.cli import COMMANDS, main


def test_version_and_help():
    runner = CliRunner()
    result = runner.invoke(main, ["--version"])
    assert result.exit_code == 0 and __version__ in result.output
    result = runner.invoke(main, ["--help"])
    assert result.exit_code == 0
    for name in COMMANDS:
        assert name in result.output


def test_every_command_loads_and_has_help():
    runner = CliRunner()
    for name in COMMANDS:
        result = runner.invoke(main, [name, "--help"])
        assert result.exit_code == 0, (name, result.output)
        assert "Usage" in result.output, name


def test_unknown_command_is_usage_error():
    result = CliRunner().invoke(main, ["frobnicate"])
    assert result.exit_code == 2 and "No such command" in result.output


def test_help_does_not_import_torch():
    code = (
        "import sys; from dali_cli.cli import main\n"
        "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
        "assert 'torch' not in sys.modules, 'dali --help imported torch'"
    )
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)


def test_tuning_options_stay_out_of_the_default_help_but_work_and_show_on_request():
    """The tuning group: hidden from `--help` unless DALI_HELP=all, and still accepted."""
    code = (
        "import click; from dali_cli.cli import main as root; "
        "ctx = click.Context(root); cmd = root.get_command(ctx, 'ptsn-sweep'); "
        "print(sorted(o.opts[0] for o in cmd.params if isinstance(o, click.Option) and o.hidden))"
    )
    hidden = {}
    for value in ("", "all"):
        env = {**os.environ, "DALI_HELP": value}
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
        hidden[value] = out.stdout.strip()
    assert "--noise" in hidden[""] and "--subsample-min" in hidden[""]
    assert hidden["all"] == "[]"
    result = CliRunner().invoke(main, ["ptsn-sweep", "--help"])
    assert "--noise" not in result.output and "DALI_HELP=all" in result.output
    # a hidden option is parsed like any other: a bad value is refused naming it
    bad = CliRunner().invoke(main, ["ptsn-sweep", "--model", ".", "--data", ".", "--noise", "x"])
    assert bad.exit_code == 2 and "--noise" in bad.output


def leaf_commands():
    """(name, click command) of every command that runs, group members by their full name."""
    import click

    pending = [(name, main.get_command(click.Context(main), name)) for name in COMMANDS]
    while pending:
        name, command = pending.pop(0)
        if isinstance(command, click.Group):
            pending += [(f"{name} {sub}", command.commands[sub]) for sub in command.commands]
        else:
            yield name, command


def visible_options(command) -> list:
    import click

    return [p for p in command.params if isinstance(p, click.Option) and not p.hidden]


def test_the_default_help_stays_short_and_every_option_has_help():
    """What `--help` shows a user: at most 250 options over every command, each explained
    (the tuning group, DALI_HELP=all, holds the rest; docs/INTERFACES.md has the table)."""
    if os.environ.get("DALI_HELP") == "all":
        return
    commands = dict(leaf_commands())
    assert len(commands) >= 20
    total = sum(len(visible_options(command)) for command in commands.values())
    assert total <= 250, total
    import click

    bare = [
        f"{name} {option.opts[0]}"
        for name, command in commands.items()
        for option in command.params
        if isinstance(option, click.Option) and not option.help
    ]
    assert not bare, bare


def test_every_option_a_help_text_names_is_listed_in_that_help():
    """A command's default --help lists each of its own options that its text names (tuning
    ones in a section of their own), so no help sends a user to an option it does not show."""
    if os.environ.get("DALI_HELP") == "all":
        return
    import click

    unlisted = []
    for name, command in leaf_commands():
        output = CliRunner().invoke(main, [*name.split(), "--help"]).output
        listed = set(re.findall(r"^  (?:-\w, )?(--[\w-]+)", output, re.MULTILINE))
        listed |= {f"--no-{flag[2:]}" for flag in listed}  # a --x/--no-x flag's record
        for param in command.params:
            if not isinstance(param, click.Option):
                continue
            for opt in (*param.opts, *param.secondary_opts):
                if re.search(rf"(?<![\w-]){re.escape(opt)}(?![\w-])", output) and opt not in listed:
                    unlisted.append(f"{name} {opt}")
    assert not unlisted, unlisted
    pseudo = CliRunner().invoke(main, ["pseudo-label", "--help"]).output
    assert "Tuning options named above:" in pseudo and "  --nms-iou" in pseudo


def test_engine_options_have_their_own_help_section():
    result = CliRunner().invoke(main, ["pseudo-label", "--help"])
    options, engine = result.output.split("Engine options:")
    assert "--device" in engine and "--executor" in engine and "--device" not in options
    assert "--score-min" in options and "DALI_HELP=all" in engine


def test_the_import_summary_names_every_importer():
    importers = main.get_command(None, "import").commands
    assert len(importers) >= 5
    for name in importers:
        assert name in COMMANDS["import"], name


def test_step_numbers_follow_the_pipeline():
    steps = ["pretrain", "ptsn-sweep", "pseudo-label", "ppcg-rc", "ppcg-cf", "retrain"]
    for number, name in enumerate(steps, 1):
        assert COMMANDS[name].startswith(f"Step {number}:"), name


def test_one_name_per_concept_across_commands_and_the_former_names_still_work():
    """The frame set a command runs on is --data, the target's mean car size --target-size and
    the training sizing of source boxes --size-norm in every command that has the concept; the
    former names (--target, --expected-size, --source-size) parse to the same parameter, and
    --help lists only the current name."""
    import click

    commands = dict(leaf_commands())
    former = {"--target": "--data", "--expected-size": "--target-size",
              "--source-size": "--size-norm"}  # fmt: skip
    for name, command in commands.items():
        for option in command.params:
            if not isinstance(option, click.Option):
                continue
            for old, new in former.items():
                if old in option.opts:
                    assert option.opts[0] == new, (name, option.opts)
                    shown = option.get_help_record(click.Context(command))[0]
                    assert old not in shown and new in shown, (name, shown)
    for name in ("ptsn-sweep", "pseudo-label", "ppcg-rc", "ppcg-cf", "register", "track-pseudo",
                 "self-train", "eval", "size-norm"):  # fmt: skip
        opts = [o.opts for o in commands[name].params if isinstance(o, click.Option)]
        assert any(o[0] == "--data" for o in opts), name
    sweep = commands["ptsn-sweep"]
    for spelling in ("--target-size", "--expected-size"):
        context = sweep.make_context("ptsn-sweep", ["--model", ".", "--data", ".", "--out", "o",
                                                    spelling, "4,1.7,1.5"])  # fmt: skip
        assert context.params["expected_size"] == "4,1.7,1.5"
    for spelling in ("--data", "--target"):
        context = commands["register"].make_context("register", [spelling, ".", "--out", "o"])
        assert context.params["target"] == "."
    missing = CliRunner().invoke(main, ["register", "--out", "o"])
    assert missing.exit_code == 2 and "'--data'" in missing.output
    assert "--target'" not in missing.output
