"""Two runs of one DALI iteration with the same seed and thread count give the same artifacts.

Runs `make iter1` twice side by side (synth, library, pretrain, ptsn-sweep, pseudo-label, ppcg-rc,
ppcg-cf, retrain, eval) on a handful of frames with THREADS=1, then compares the weights, the
pseudo boxes and every other file (bench/tools/compare_runs.py: byte for byte but the records of
the run itself: timings, paths, dates): an unseeded draw, an order that follows the file system
or the scheduler, or a thread count taken from the machine shows up as a difference.
"""

from __future__ import annotations

import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pyarrow.parquet as pq
import pytest
import torch
from test_pipeline_smoke import REPO, VENV
from test_pipeline_smoke import pytestmark as pytestmark  # slow; needs make and the venv


def make_iter1(run: Path) -> subprocess.CompletedProcess:
    command = ["make", "--no-print-directory", "-C", str(REPO), "iter1", f"VENV={VENV}",
               f"RUN={run}", "FRAMES=4", "EPOCHS=1", "SCORE_MIN=0.0", "LIBRARY_MODELS=3",
               "SYNTH_WORKERS=1", "THREADS=1"]  # fmt: skip
    return subprocess.run(command, capture_output=True, text=True, timeout=1200)


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("repeat")
    runs = (root / "a", root / "b")
    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(make_iter1, runs))
    for result in results:
        assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return runs


def test_both_runs_wrote_the_same_weights(two_runs):
    a, b = two_runs
    for model in ("iter0/model/model.pt", "iter1/model/model.pt"):
        first = torch.load(a / model, map_location="cpu", weights_only=True)
        second = torch.load(b / model, map_location="cpu", weights_only=True)
        assert first.keys() == second.keys(), model
        for name in first:
            assert torch.equal(first[name], second[name]), f"{model}: {name} differs"


def test_both_runs_kept_the_same_pseudo_boxes(two_runs):
    first, second = (pq.read_table(run / "iter1/pseudo/boxes.parquet") for run in two_runs)
    assert first.num_rows > 0, "no pseudo box: the comparison would prove nothing"
    assert first.equals(second)


def test_every_stage_wrote_the_same_artifacts(two_runs):
    tool = REPO / "bench" / "tools" / "compare_runs.py"
    result = subprocess.run(
        [sys.executable, str(tool), *map(str, two_runs)], capture_output=True, text=True
    )
    assert result.returncode == 0, result.stdout[-3000:]
    assert "identical" in result.stdout
