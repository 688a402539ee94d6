"""`make real-kitti`'s plan (`make -n`, nothing runs): only `dali eval` and the bench diagnostics
read the drive's tracklets; the DALI stages and the control adapt to the unlabeled drive, the sim
oracle trains on synthetic frames, and every row is evaluated on the drive and on the object
frames."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")


@pytest.fixture(scope="module")
def commands(tmp_path_factory) -> list[str]:
    run = tmp_path_factory.mktemp("real") / "run"
    result = subprocess.run(
        ["make", "--no-print-directory", "-n", "-C", str(REPO), "real-kitti", f"REAL_RUN={run}",
         "REAL_DRIVE=/data/2011_09_26/2011_09_26_drive_0001_sync"],
        capture_output=True, text=True, timeout=60, check=True,
    )  # fmt: skip
    lines = [line for line in result.stdout.splitlines() if "/bin/dali " in line]
    return [line.split("/bin/dali ", 1)[1] for line in lines] + [
        line for line in result.stdout.splitlines() if "bench/" in line
    ]


def test_only_eval_and_bench_read_the_tracklets(commands):
    readers = [line for line in commands if "drive_labels" in line]
    assert readers
    for line in readers:
        assert line.startswith(("eval ", "import kitti-raw ")) or "bench/" in line, line
        if line.startswith("import kitti-raw "):
            assert "--no-labels" not in line and "--out" in line and "drive_labels" in line
    unlabeled = [line for line in commands if line.startswith("import kitti-raw ")]
    assert any(
        "--no-labels" in line and line.rstrip().endswith("/data/drive") for line in unlabeled
    )


def test_dali_stages_adapt_to_the_unlabeled_drive(commands):
    stages = ("ptsn-sweep", "pseudo-label", "ppcg-rc", "ppcg-cf", "self-train")
    for line in commands:
        if line.split(" ", 1)[0] in stages:
            assert "/data/drive " in line + " " and "drive_labels" not in line, line
    oracle = [
        line for line in commands if "sim_oracle_x2_budget/model" in line and "pretrain" in line
    ]
    assert len(oracle) == 1 and "--source " in oracle[0] and "/data/target " in oracle[0] + " "


def test_every_row_is_evaluated_on_both_sets(commands):
    evals = [line for line in commands if line.startswith("eval ")]
    on_drive = [line for line in evals if "--data" in line and "drive_labels" in line]
    on_objects = [line for line in evals if "/data/objects" in line]
    assert len(on_drive) == len(on_objects) == 7
    assert all("--protocol kitti" in line for line in evals)
