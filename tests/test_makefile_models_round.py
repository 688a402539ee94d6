"""`make models-round`'s plan (`make -n`, nothing trains): the shipped models/kitti-hdl64e sweeps
its own scale on the real target, pseudo-labels it there, its labels are tracked over the
registered scans and it self-trains on them from itself; the gate against the shipped model runs
before the card replaces it, and no source is trained."""

from __future__ import annotations

import re
import shlex
import shutil

import pytest
from make_plans import make, option

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")

LABELLED = "data/raw/2011_09_26/2011_09_26_drive_0001_sync"
DRIVES = (LABELLED, "data/scans/2011_09_26/2011_09_26_drive_0005_sync")
MODEL = "models/kitti-hdl64e"


@pytest.fixture(scope="module")
def plan(tmp_path_factory) -> dict:
    """`make -n models-round` over two raw drives and object frames with a drive table."""
    root = tmp_path_factory.mktemp("round")
    (root / "kitti" / "training").mkdir(parents=True)
    table = ["id\traw_drive", "000001\t2011_09_26_drive_0005_sync",
             "000002\t2011_10_03_drive_0047_sync"]  # fmt: skip
    (root / "kitti" / "frames.tsv").write_text("\n".join(table) + "\n")
    result = make("-n", "models-round", f"REAL_RUN={root / 'run'}", f"REAL_DRIVE={LABELLED}",
                  f"REAL_DRIVES={' '.join(DRIVES)}", f"REAL_OBJECTS={root / 'kitti' / 'training'}")  # fmt: skip
    assert result.returncode == 0, result.stderr
    joined = result.stdout.replace("\\\n", " ").splitlines()  # continuation lines joined
    dali = [shlex.split(line.split("/bin/dali ", 1)[1]) for line in joined if "/bin/dali " in line]
    by_out = {}
    for words in dali:
        by_out.setdefault(option(words, "--out"), words)
    return {"round": f"{root}/run-round", "data": f"{root}/run-data", "lines": joined,
            "dali": dali, "by_out": by_out}  # fmt: skip


def test_the_shipped_model_labels_the_target_at_its_own_new_scale(plan):
    by_out, run, data = plan["by_out"], plan["round"], plan["data"]
    sweep = by_out[f"{run}/ptsn"]
    assert sweep[0] == "ptsn-sweep" and option(sweep, "--model") == MODEL
    assert option(sweep, "--data") == f"{data}/target"
    labels = by_out[f"{run}/pseudo_low"]
    assert option(labels, "--model") == MODEL and option(labels, "--scale-from") == f"{run}/ptsn"
    assert option(labels, "--score-min") == "0.1"
    tracked = by_out[f"{run}/tracked"]
    assert option(tracked, "--pseudo") == f"{run}/pseudo_low"
    assert option(tracked, "--poses") == f"{data}/target_poses"


def test_it_self_trains_from_itself_on_its_tracked_labels_and_trains_no_source(plan):
    model = plan["by_out"][f"{plan['round']}/model"]
    assert model[0] == "self-train" and option(model, "--init") == MODEL
    assert option(model, "--pseudo") == f"{plan['round']}/tracked"
    assert option(model, "--seed") == "0" and option(model, "--epochs") == "6"
    assert not any(words[0] in ("pretrain", "retrain", "synth") for words in plan["dali"])


def test_the_gate_runs_before_the_card_replaces_the_shipped_model(plan):
    lines, run, data = plan["lines"], plan["round"], plan["data"]
    gate = next(i for i, line in enumerate(lines) if "model_gate.py" in line)
    card = next(i for i, line in enumerate(lines) if "model_card.py" in line)
    assert gate < card
    assert re.search(r"--shipped (\S+)", lines[gate]).group(1) == MODEL
    assert re.search(r"--candidate (\S+)", lines[gate]).group(1) == f"{run}/model"
    assert f"--candidate-scale-from {run}/ptsn" in lines[gate]
    assert f"--set drive={data}/drive_labels" in lines[gate]
    assert f"--set objects_adapted={data}/objects_adapted" in lines[gate]
    assert re.search(r"--out (\S+)", lines[card]).group(1) == MODEL
    assert f"--model {run}/model --scale-from {run}/ptsn" in lines[card]
    assert f"--gate {run}/model_gate.json" in lines[card]
    assert f"--eval drive={run}/eval/drive" in lines[card] and "--recipe-note" in lines[card]
    evaluation = plan["by_out"][f"{run}/eval/objects_other"]
    assert option(evaluation, "--model") == f"{run}/model"
    assert option(evaluation, "--data") == f"{data}/objects_other"
    assert option(evaluation, "--scale-from") == f"{run}/ptsn"
