"""Every stage through the Makefile on a handful of synthetic frames (the CI smoke run).

Runs `make iter1` in a temporary RUN directory with tiny sizes, checks each artifact and its
manifest, that test-time evaluation wrote both IoU blocks, that `dali report` reads the run, and
that a second `make iter1` does nothing.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from dali_cli.store.artifacts import read_boxes

REPO = Path(__file__).resolve().parents[1]
VENV = Path(sys.prefix)

pytestmark = [
    pytest.mark.slow,  # every stage through make, end to end
    pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed"),
    pytest.mark.skipif(
        not (VENV / ".installed").is_file() or not (VENV / "bin" / "dali").is_file(),
        reason="run through `make test-slow` (needs the venv the Makefile installs)",
    ),
]

STAGES = {  # stage directory -> the stage name its manifest records
    "data/source": "synth",
    "data/target": "synth",
    "data/target_val": "synth",
    "library": "library",
    "iter0/model": "pretrain",
    "iter1/ptsn": "ptsn_sweep",
    "iter1/pseudo": "pseudo_label",
    "iter1/rc": "ppcg_rc",
    "iter1/cf": "ppcg_cf",
    "iter1/model": "retrain",
    "iter2/ptsn": "ptsn_sweep",
}
EVALS = ("iter0/eval/metrics.json", "iter0/eval_ptsn/metrics.json", "iter1/eval/metrics.json")


def make(run: Path, *goals: str, check: bool = True) -> subprocess.CompletedProcess:
    command = [
        "make",
        "--no-print-directory",
        "-C",
        str(REPO),
        *goals,
        f"VENV={VENV}",
        f"RUN={run}",
        "FRAMES=4",
        "EPOCHS=1",
        "SCORE_MIN=0.0",
        "LIBRARY_MODELS=3",
        "SYNTH_WORKERS=1",
    ]
    return subprocess.run(command, capture_output=True, text=True, check=check, timeout=600)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("pipeline") / "run"
    result = make(run, "iter1", check=False)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return run


def test_every_stage_wrote_its_artifact_and_manifest(tiny_run):
    for directory, stage in STAGES.items():
        manifest_path = tiny_run / directory / "manifest.json"
        assert manifest_path.is_file(), f"{directory}: no manifest"
        manifest = json.loads(manifest_path.read_text())
        assert manifest["stage"] == stage, directory
        assert manifest["dali_version"]
        assert manifest["timings"]["wall_seconds"] >= 0
        assert manifest["outputs"]["files"] > 0
        for name, records in manifest["inputs"].items():
            for record in records:
                assert len(record["hash"]) >= 16, f"{directory}: input {name} without a hash"
    # no temporary directories left behind by the atomic writes
    leftovers = [p for p in tiny_run.rglob("*") if ".tmp-" in p.name or p.name.endswith(".part")]
    assert leftovers == []


def test_stages_chain_their_inputs_by_content(tiny_run):
    def manifest(directory):
        return json.loads((tiny_run / directory / "manifest.json").read_text())

    pseudo, rc, retrain = manifest("iter1/pseudo"), manifest("iter1/rc"), manifest("iter1/model")
    assert rc["inputs"]["boxes"][0]["hash"] == pseudo["content_hash"]
    ppcg_hashes = {record["hash"] for record in retrain["inputs"]["ppcg"]}
    assert ppcg_hashes == {
        manifest("iter1/rc")["content_hash"],
        manifest("iter1/cf")["content_hash"],
    }
    scale = json.loads((tiny_run / "iter1/ptsn/scale.json").read_text())["scale"]
    assert 0.8 <= scale <= 1.4  # the Makefile's default sweep bounds


def test_evaluations_have_both_iou_blocks_and_sizes(tiny_run):
    for relative in EVALS:
        metrics = json.loads((tiny_run / relative).read_text())
        assert metrics["Car"]["iou"] == 0.7 and metrics["Car@0.5"]["iou"] == 0.5, relative
        assert metrics["Car"]["protocol"] == "range" and metrics["Car"]["front_only"]
        assert metrics["Car"]["frames"] == 4
        gt = metrics["sizes"]["gt"]
        assert gt is not None and 3.0 < gt[0] < 5.0  # KITTI-like target cars
        predictions = read_boxes(tiny_run / relative.replace("metrics.json", "predictions.parquet"))
        assert set(predictions.frame_id) <= {f"{i:06d}" for i in range(4)}
    ptsn_scale = json.loads((tiny_run / "iter1/ptsn/scale.json").read_text())["scale"]
    assert json.loads((tiny_run / EVALS[1]).read_text())["scale"] == pytest.approx(ptsn_scale)
    assert json.loads((tiny_run / EVALS[0]).read_text())["scale"] == 1.0


def test_report_reads_the_run(tiny_run):
    dali = VENV / "bin" / "dali"
    result = subprocess.run([str(dali), "report", str(tiny_run)], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "| Source only |" in result.stdout and "| PTSN + RC&CF (x1) |" in result.stdout
    document = json.loads((tiny_run / "report" / "report.json").read_text())
    rows = {row["name"]: row for row in document["target"]}
    assert set(rows["PTSN + RC&CF (x1)"]["ap"]) == {"0.7", "0.5"}
    assert rows["Oracle"]["ap"] == {}  # not run in the smoke run: shown as missing, not invented
    drawn = {Path(path).name for path in document["plots"]}
    expected = {"ptsn_curves.png", "pseudo_sizes.png", "method_sizes.png", "bev_views.png"}
    assert expected | {"ppcg_iter1.png"} <= drawn
    assert all((tiny_run / "report" / "plots" / name).stat().st_size > 10_000 for name in drawn)


def test_second_make_does_nothing(tiny_run):
    manifests = sorted(tiny_run.rglob("manifest.json"))
    before = {path: path.stat().st_mtime_ns for path in manifests}
    assert make(tiny_run, "-q", "iter1", check=False).returncode == 0  # up to date
    result = make(tiny_run, "iter1")
    assert "dali" not in result.stdout, result.stdout
    assert {path: path.stat().st_mtime_ns for path in manifests} == before
