"""Plans of the Makefile for tests: what `make` would run, without running it (a test helper)."""

from __future__ import annotations

import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def make(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    """`make ARGS` in the repository root, output captured."""
    return subprocess.run(
        ["make", "--no-print-directory", "-C", str(ROOT), *args],
        capture_output=True, text=True, env=env,
    )  # fmt: skip


def dali_commands(*args: str) -> list[str]:
    """The dali commands of `make -n ARGS`, in order (the plan from scratch: nothing is built)."""
    run = make("-n", *args)
    assert run.returncode == 0, run.stderr
    return [line.strip() for line in run.stdout.splitlines() if "dali " in line]


def option(words: list[str], name: str) -> str | None:
    return words[words.index(name) + 1] if name in words else None


def values(words: list[str], name: str) -> list[str]:
    """Every value of a repeated option, in order."""
    return [words[i + 1] for i, word in enumerate(words[:-1]) if word == name]


def options(words: list[str], skip: tuple[str, ...]) -> list[str]:
    """The words of a command without the options `skip` and their values."""
    kept, drop = [], False
    for word in words:
        if drop:
            drop = False
        elif word in skip:
            drop = True
        else:
            kept.append(word)
    return kept


def named(commands, *verb: str) -> list[list[str]]:
    return [words for words in commands if tuple(words[: len(verb)]) == verb]
