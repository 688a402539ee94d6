"""The Makefile's recursive makes (kitti-protocol, demo, experiment) use the same Makefile as the
top-level one: the job scripts under docs/results run `make -f PATH/Makefile` from the directory
that holds their runs/ and a .venv, where there is no Makefile (otherwise kitti-protocol stops
there with "No rule to make target")."""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")


def test_kitti_protocol_from_another_directory_plans_the_kitti_row(tmp_path):
    """A finished iteration-0 row, oldest input first, in a directory without a Makefile."""
    run = tmp_path / "run"
    files = [".venv/.installed", "run/data/source/manifest.json",
             "run/data/target_val/manifest.json", "run/iter0/model/manifest.json",
             "run/iter0/eval/manifest.json", "run/iter0/eval/metrics.json",
             "run/iter0/eval/predictions.parquet"]  # fmt: skip
    now = time.time()
    for age, name in enumerate(reversed(files)):
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("{}")
        os.utime(path, (now - age, now - age))
    result = subprocess.run(
        ["make", "--no-print-directory", "-n", "-f", str(REPO / "Makefile"), "kitti-protocol",
         "RUN=run"],
        cwd=tmp_path, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    kitti = [line for line in result.stdout.splitlines() if "--protocol kitti" in line]
    assert [line.split("--out ")[-1].strip() for line in kitti] == [
        "run/iter0/eval/metrics_kitti.json"
    ], result.stdout
    assert not (run / "iter0" / "eval" / "metrics_kitti.json").exists()  # -n: nothing ran
