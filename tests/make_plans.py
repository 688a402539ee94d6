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
