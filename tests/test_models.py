"""The shipped models (models/<name>/, `make models`): each is a dali model directory small
enough to ship with a card whose figures reproduce, and bench/model_card.py, which writes them,
never replaces a directory it did not write."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from dali_cli.cli import main

ROOT = Path(__file__).resolve().parent.parent
MODELS = ROOT / "models"
# every directory of models/ with a card; the two below always ship
SHIPPED = tuple(sorted(d.name for d in MODELS.iterdir() if (d / "card.json").is_file()))
# the adapted models: those with a test-time scale; a sparse one (kitti-<N>beam) reads its test
# frame thinned to N beams, as its own recipe did
ADAPTED = tuple(name for name in SHIPPED if (MODELS / name / "scale.json").is_file())
FIXTURE = ROOT / "tests" / "fixtures" / "real" / "kitti" / "training"
MAX_BYTES = 20 * 1024 * 1024
CARD_SCRIPT = ROOT / "bench" / "model_card.py"


def card_of(name: str) -> dict:
    return json.loads((MODELS / name / "card.json").read_text())


def test_the_source_and_the_kitti_model_ship():
    assert {"waymo-like-source", "kitti-hdl64e"} <= set(SHIPPED) and "kitti-hdl64e" in ADAPTED


def beams_of(name: str) -> list[str]:
    """`--beams N` for kitti-<N>beam, nothing for the full scans' models."""
    match = re.fullmatch(r"kitti-(\d+)beam", name)
    return ["--beams", match.group(1)] if match else []


@pytest.mark.parametrize("name", SHIPPED)
def test_a_shipped_model_is_a_small_dali_model_with_its_card(name):
    directory = MODELS / name
    assert (directory / "model.pt").stat().st_size <= MAX_BYTES
    config = json.loads((directory / "model.json").read_text())
    assert config["detector"] and config["config"]["x_range_m"]
    card = card_of(name)
    assert card["name"] == name and card["model_bytes"] == (directory / "model.pt").stat().st_size
    assert card["evaluations"] and card["provenance"]
    readme = (directory / "README.md").read_text()
    assert f"# {name}:" in readme and "## How it was made" in readme
    if (directory / "scale.json").is_file():
        assert json.loads((directory / "scale.json").read_text())["scale"] == card["scale"]


@pytest.mark.parametrize("name", ADAPTED)
def test_no_real_label_went_into_the_adapted_model(name):
    """Every stage that made an adapted model read scans only: each real import holds no label."""
    stages = card_of(name)["provenance"]
    imports = [step for step in stages if step["stage"].startswith("import")]
    assert imports
    for step in imports:
        assert step["counts"]["frames_without_labels"] == step["counts"]["frames"] > 0
    assert not any(step["stage"] in ("eval", "compare") for step in stages)


@pytest.mark.parametrize("name", ADAPTED)
def test_the_adapted_model_reproduces_its_cards_figure_on_the_test_frame(tmp_path, name):
    """`dali eval` of an adapted model with its own scale on the repository's KITTI frame
    (thinned to its beams) gives the AP its card states, within 0.1."""
    runner = CliRunner()
    data, out = tmp_path / "frame", tmp_path / "eval"
    result = runner.invoke(main, ["import", "kitti", str(FIXTURE), "--crop-fov", *beams_of(name),
                                  "--no-progress", "--out", str(data)])  # fmt: skip
    assert result.exit_code == 0, result.output
    model = MODELS / name
    result = runner.invoke(main, ["eval", "--model", str(model), "--data", str(data), "--scale-from",
                                  str(model), "--protocol", "kitti", "--iou", "0.7", "--iou", "0.5",
                                  "--no-progress", "--out", str(out)])  # fmt: skip
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    stated = card_of(name)["fixture"]
    for block, kind, header in (("Car", "bev", "AP_BEV@0.7"), ("Car", "3d", "AP_3D@0.7"),
                                ("Car@0.5", "bev", "AP_BEV@0.5"), ("Car@0.5", "3d", "AP_3D@0.5")):  # fmt: skip
        assert metrics[block][kind]["moderate"] == pytest.approx(stated[header], abs=0.1)
    scores = pq.read_table(out / "predictions.parquet", columns=["score"]).column(0).to_numpy()
    assert len(scores) == stated["predictions"]["boxes"]
    assert scores.sum() == pytest.approx(stated["predictions"]["score_sum"], abs=1e-3)


def fake_model(directory: Path) -> Path:
    """A directory with the files a card copies and a manifest naming one input."""
    directory.mkdir(parents=True)
    (directory / "model.pt").write_bytes(b"weights")
    (directory / "model.json").write_text(json.dumps({"detector": "x", "config": {}}))
    source = directory.parent / "source"
    source.mkdir()
    (source / "manifest.json").write_text(json.dumps({"stage": "synth", "params": {"frames": 3}}))
    manifest = {"stage": "pretrain", "params": {"epochs": 2.0, "lr": 0.1, "batch_size": 1},
                "inputs": {"source": [{"path": str(source), "hash": "0"}]},
                "outputs": {"counts": {"frames_seen": 6, "steps": 6}},
                "timings": {"wall_seconds": 12.0},
                "runtime": {"cpu_model": "CPU", "device": "cpu", "threads": 1}}  # fmt: skip
    (directory / "manifest.json").write_text(json.dumps(manifest))
    return directory


def fake_eval(directory: Path, bev: float) -> Path:
    directory.mkdir(parents=True)
    block = {"protocol": "kitti", "frames": 2, "bev": {"moderate": bev}, "3d": {"moderate": 1.0}}
    (directory / "metrics.json").write_text(json.dumps({"Car": block, "Car@0.5": block}))
    return directory


def run_card(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(CARD_SCRIPT), *args], capture_output=True, text=True)


def test_the_card_names_every_stage_and_the_recipes_spread(tmp_path):
    model = fake_model(tmp_path / "run" / "model")
    evals = [fake_eval(tmp_path / f"eval{i}", bev) for i, bev in enumerate((50.0, 60.0, 70.0))]
    out = tmp_path / "models" / "m"
    args = ["--model", str(model), "--name", "m", "--title", "t", "--summary", "s",
            "--eval", f"set={evals[0]}", "--recipe", f"set={','.join(map(str, evals))}",
            "--limit", "one", "--out", str(out)]  # fmt: skip
    done = run_card(*args)
    assert done.returncode == 0, done.stderr
    card = json.loads((out / "card.json").read_text())
    assert [step["stage"] for step in card["provenance"]] == ["synth", "pretrain"]
    assert card["provenance"][1]["params"] == {"epochs": 2.0, "lr": 0.1}
    assert card["recipe_seeds"] == 3 and card["evaluations"]["set"]["AP_BEV@0.7"] == 50.0
    readme = (out / "README.md").read_text()
    assert "| set | 3 | 60.0 ± 10.0 |" in readme and "- one" in readme
    assert (out / "model.pt").read_bytes() == b"weights"
    # rewriting its own directory replaces it; nothing is left beside it
    assert run_card(*args).returncode == 0
    assert sorted(p.name for p in out.parent.iterdir()) == ["m"]


def test_a_model_adapted_from_a_shipped_one_carries_the_shipped_cards_stages(tmp_path):
    """Self-training from models/<name> (a card, no manifest) puts that card's provenance first,
    then the stages that adapted it further."""
    shipped = tmp_path / "models" / "base"
    shipped.mkdir(parents=True)
    step = {"params": {}, "counts": {}, "wall_seconds": 1.0, "machine": "", "created": None}
    earlier = [{**step, "stage": "synth", "directory": "s0/data/source"},
               {**step, "stage": "pretrain", "directory": "s0/source/model"}]  # fmt: skip
    (shipped / "card.json").write_text(json.dumps({"provenance": earlier}))
    model = tmp_path / "round" / "model"
    model.mkdir(parents=True)
    (model / "model.pt").write_bytes(b"weights")
    (model / "model.json").write_text(json.dumps({"detector": "x", "config": {}}))
    (model / "manifest.json").write_text(json.dumps(
        {"stage": "self_train", "params": {"epochs": 6.0},
         "inputs": {"init": [{"path": str(shipped), "hash": "0"}]}}))  # fmt: skip
    out = tmp_path / "models" / "next"
    done = run_card("--model", str(model), "--name", "next", "--title", "t", "--summary", "s",
                    "--out", str(out))  # fmt: skip
    assert done.returncode == 0, done.stderr
    stages = json.loads((out / "card.json").read_text())["provenance"]
    assert [step["stage"] for step in stages] == ["synth", "pretrain", "self_train"]


def test_the_card_shows_how_the_true_positives_face_and_fit(tmp_path):
    """The backwards count, the median |length error| and the length spread come from the
    evaluation's heading and error blocks; an evaluation without them gets no such row."""
    model = fake_model(tmp_path / "run" / "model")
    fitted, older = fake_eval(tmp_path / "fitted", 80.0), fake_eval(tmp_path / "older", 70.0)
    metrics = json.loads((fitted / "metrics.json").read_text())
    metrics["Car"]["heading"] = {"moderate": {"tp": 40, "backwards": 3}}
    metrics["errors"] = {"true_positives": {"all": {"l_m": {"median_abs": 0.1734}},
                                            "sizes": {"l_m": {"spread_ratio": 0.231}}}}  # fmt: skip
    (fitted / "metrics.json").write_text(json.dumps(metrics))
    out = tmp_path / "models" / "m"
    done = run_card("--model", str(model), "--name", "m", "--title", "t", "--summary", "s",
                    "--eval", f"fitted={fitted}", "--eval", f"older={older}", "--out", str(out))  # fmt: skip
    assert done.returncode == 0, done.stderr
    card = json.loads((out / "card.json").read_text())["evaluations"]
    assert card["fitted"]["backwards"] == "3/40" and card["fitted"]["|dl| m"] == 0.173
    assert card["fitted"]["l spread"] == 0.23 and "backwards" not in card["older"]
    readme = (out / "README.md").read_text()
    assert (
        "| fitted | 3/40 | 0.173 | 0.23 |" in readme
        and "| older | " not in readme.split("How the found cars")[1].split("##")[0]
    )


def test_the_cards_use_line_names_the_front_view_detect_defaults_to(tmp_path):
    """A model adapted on cropped scans (model.json's config front_deg) runs in that view by
    default: its card's Use says so and how to see every point; a full-scan model's does not."""
    for front in (None, 75.0):
        model = fake_model(tmp_path / str(front) / "run" / "model")
        (model / "model.json").write_text(
            json.dumps({"detector": "x", "config": {"front_deg": front}})
        )
        out = tmp_path / str(front) / "models" / "m"
        done = run_card("--model", str(model), "--name", "m", "--title", "t", "--summary", "s",
                        "--eval", f"set={fake_eval(tmp_path / str(front) / 'eval', 50.0)}",
                        "--out", str(out))  # fmt: skip
        assert done.returncode == 0, done.stderr
        detect = json.loads((out / "card.json").read_text())["use"].splitlines()[0]
        assert detect.startswith("dali detect") and detect in (out / "README.md").read_text()
        assert ("front 75°" in detect and "--front-deg 360" in detect) == (front is not None)
        assert ("front" in detect) == (front is not None)


def test_a_directory_the_card_did_not_write_is_never_replaced(tmp_path):
    model = fake_model(tmp_path / "run" / "model")
    evaluation = fake_eval(tmp_path / "eval", 50.0)
    out = tmp_path / "models" / "m"
    out.mkdir(parents=True)
    (out / "notes.txt").write_text("mine")
    done = run_card("--model", str(model), "--name", "m", "--title", "t", "--summary", "s",
                    "--eval", f"set={evaluation}", "--out", str(out))  # fmt: skip
    assert done.returncode != 0 and "not replaced" in done.stderr
    assert sorted(p.name for p in out.parent.iterdir()) == ["m"]
    assert (out / "notes.txt").read_text() == "mine"


def test_a_set_too_small_for_r40_gets_its_ceiling_and_r400_on_the_card(tmp_path):
    """4 counted cars cap AP_R40 at 7.5: the card says so and gives the model's R400 AP, which
    the card computes from the evaluation's saved predictions and the data it evaluated."""
    from dali_cli.store.artifacts import BoxTable, write_boxes
    from tests.test_evaluate import kitti_columns, row_of_cars

    cars, kitti = row_of_cars(4), kitti_columns(4)
    data = tmp_path / "data"
    data.mkdir()
    write_boxes(data, BoxTable.from_arrays(["f"] * 4, cars, label="Car", **kitti))
    evaluation = fake_eval(tmp_path / "eval", 7.5)
    metrics = json.loads((evaluation / "metrics.json").read_text())
    metrics["Car"]["counts"] = {"moderate": {"gt": 4}}
    (evaluation / "metrics.json").write_text(json.dumps(metrics))
    found = BoxTable.from_arrays(["f"] * 3, cars[:3], score=[0.9, 0.8, 0.7], label="Car")
    write_boxes(evaluation, found).rename(evaluation / "predictions.parquet")
    inputs = {"inputs": {"data": [{"path": str(data), "hash": "0"}]}}
    (evaluation / "manifest.json").write_text(json.dumps(inputs))
    out = tmp_path / "models" / "m"
    done = run_card("--model", str(fake_model(tmp_path / "run" / "model")), "--name", "m",
                    "--title", "t", "--summary", "s", "--eval", f"small={evaluation}",
                    "--out", str(out))  # fmt: skip
    assert done.returncode == 0, done.stderr
    readme = (out / "README.md").read_text()
    assert "On small only 4 moderate cars count, so KITTI's R40 caps AP at 7.5" in readme
    assert "AP_BEV / AP_3D@0.7 is 75.0 / 75.0" in readme  # 3 of 4 found, no false box
