"""`make bench` runs every benchmark in bench/ and nothing that needs arguments: each script it
names exists and answers --help, and every other script in bench/ is an analysis tool that
refuses to run without its run directories (so none is a forgotten benchmark)."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")


def benchmark_runs() -> list[list[str]]:
    """`make bench`'s runs as argument lists [script, args...], from its own recipe (`make -n`)."""
    plan = subprocess.run(
        ["make", "--no-print-directory", "-n", "-C", str(REPO), "bench"],
        capture_output=True, text=True, timeout=60, check=True,
    ).stdout  # fmt: skip
    loop = re.search(r"for run in (.*?); do", plan)
    assert loop, plan
    return [run.split(":") for run in loop.group(1).split()]


def run(script: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(REPO / "bench" / script), *args],
        capture_output=True, text=True, timeout=120, cwd=REPO,
    )  # fmt: skip


def test_every_benchmark_make_bench_runs_exists_and_takes_its_arguments():
    runs = benchmark_runs()
    assert len(runs) >= 10
    for script, *args in runs:
        assert (REPO / "bench" / script).is_file(), script
        result = run(script, *args, "--help")
        assert result.returncode == 0, f"bench/{script} {' '.join(args)}: {result.stderr[-500:]}"


def test_the_other_bench_scripts_are_tools_that_need_arguments():
    listed = {script for script, *_ in benchmark_runs()}
    tools = sorted(p.name for p in (REPO / "bench").glob("*.py") if p.name not in listed)
    assert tools  # paired_rows.py, pseudo_labels.py, ...
    for script in tools:
        result = run(script)
        assert result.returncode == 2, (  # a usage error, as argparse exits
            f"bench/{script} runs without arguments: add it to the Makefile's BENCHMARKS"
        )
