"""`make real-kitti-beams`'s plan (`make -n`, nothing trains): models/kitti-hdl64e adapted to the
target's drives imported at 16 beams into a data directory of their own, every row built by the
targets of `make real-kitti` from the shipped model (no pretraining), the control self-trained on
the model's tracked pseudo labels with x2's budget, the upper reference on the 64-beam sets; and
without BEAMS, `make real-kitti`'s plan as before."""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess

import pytest
from make_plans import ROOT, dali_commands, make, named, option, options

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")

LABELLED = "data/raw/2011_09_26/2011_09_26_drive_0001_sync"
DRIVES = (LABELLED, "data/scans/2011_09_26/2011_09_26_drive_0005_sync")
MODEL = "models/kitti-hdl64e"
SEEDS = ("0", "1")
SETS = ("objects_adapted", "objects_other")
ROWS = {  # row -> (model, drive evaluation, scale flag and value)
    "direct": (MODEL, "iter0/eval_direct", ("--scale-from", MODEL)),
    "ptsn": (MODEL, "iter0/eval_ptsn", ("--scale-from", "iter1/ptsn")),
    "x1": ("iter1/model", "iter1/eval", ("--scale-from", "iter2/ptsn")),
    "x2": ("iter2/model", "iter2/eval", ("--scale-from", "iter3/ptsn")),
    "control": (
        "baselines/source_x2_budget/model",
        "baselines/source_x2_budget/eval_ptsn",
        ("--scale-from", "baselines/source_x2_budget/ptsn"),
    ),
    "control_tst": (
        "baselines/source_x2_budget_tst/model",
        "baselines/source_x2_budget_tst/eval",
        ("--scale-from", "baselines/source_x2_budget/ptsn"),
    ),
    "x2_tst": ("iter2_tst/model", "iter2_tst/eval", ("--scale-from", "iter3/ptsn")),
    "dense_tst": ("dense_tst/model", "dense_tst/eval", ("--scale-from", MODEL)),
}


def commands_of(lines: list[str]) -> list[list[str]]:
    return [shlex.split(line.split("/bin/dali ", 1)[1]) for line in lines]


@pytest.fixture(scope="module")
def plan(tmp_path_factory) -> dict:
    """`make -n real-kitti-beams BEAMS=16` over two raw drives and object frames with a table."""
    root = tmp_path_factory.mktemp("beams")
    (root / "kitti" / "training").mkdir(parents=True)
    table = [
        "id\traw_drive",
        "000001\t2011_09_26_drive_0005_sync",
        "000002\t2011_10_03_drive_0047_sync",
    ]
    (root / "kitti" / "frames.tsv").write_text("\n".join(table) + "\n")
    variables = [
        f"REAL_RUN={root / 'run'}",
        f"REAL_DRIVE={LABELLED}",
        f"REAL_DRIVES={' '.join(DRIVES)}",
        f"REAL_OBJECTS={root / 'kitti' / 'training'}",
        f"SEEDS={' '.join(SEEDS)}",
    ]
    lines = dali_commands("real-kitti-beams", "BEAMS=16", *variables)
    return {
        "root": root,
        "data": f"{root}/run-16beams-data",
        "variables": variables,
        "lines": lines,
        "commands": commands_of(lines),
    }


def test_every_import_is_at_16_beams_into_the_beams_data(plan):
    data, commands = plan["data"], plan["commands"]
    imports = {option(w, "--out"): w for w in named(commands, "import")}
    outs = {f"{data}/drives/2011_09_26_drive_0001", f"{data}/drives/2011_09_26_drive_0005"}
    outs |= {f"{data}/drive_tracklets"} | {f"{data}/{name}" for name in SETS}
    assert outs <= set(imports)
    for out in outs:
        assert option(imports[out], "--beams") == "16", out
    for out in outs - {f"{data}/drive_tracklets", *(f"{data}/{name}" for name in SETS)}:
        assert "--no-labels" in imports[out] and "--crop-fov" in imports[out]
    # the only other imports: the full scans of the drives (the dense teacher's) and the upper
    # reference's 64-beam sets, where `make real-kitti` has them
    others = set(imports) - outs
    full = {f"{plan['root']}/run-data/drives/{name}" for name in ("2011_09_26_drive_0001",
                                                                  "2011_09_26_drive_0005")}  # fmt: skip
    assert others == full | {
        f"{plan['root']}/run-data/{name}" for name in ("drive_tracklets", *SETS)
    }
    assert not any("--beams" in imports[out] for out in others)
    merges = {option(w, "--out"): w for w in named(commands, "merge")}
    assert f"{data}/target" in merges and "--no-labels" in merges[f"{data}/target"]


def test_the_rows_start_from_the_shipped_model_without_pretraining(plan):
    data, commands = plan["data"], plan["commands"]
    assert not named(commands, "pretrain")
    for seed in SEEDS:
        run = f"{plan['root']}/run-16beams-kitti-hdl64e-s{seed}"
        by_out = {option(w, "--out"): w for w in commands}
        assert option(by_out[f"{run}/iter1/ptsn"], "--model") == MODEL
        assert option(by_out[f"{run}/iter1/pseudo"], "--model") == MODEL
        assert option(by_out[f"{run}/iter1/model"], "--init") == MODEL
        assert option(by_out[f"{run}/iter2/model"], "--init") == f"{run}/iter1/model"
        # PPCG ray-casts the thinned sensor; every adapting stage reads the 16-beam target
        for stage in ("rc", "cf"):
            assert option(by_out[f"{run}/iter1/{stage}"], "--target-profile") == "kitti-16"
    adapting = [
        w
        for w in commands
        if w[0] in ("ptsn-sweep", "pseudo-label", "ppcg-rc", "self-train")
        and "/dense/" not in option(w, "--out")  # the dense teacher labels the full scans
    ]
    assert adapting and all(option(w, "--data") == f"{data}/target" for w in adapting)


def test_every_row_is_evaluated_on_every_set_at_its_drive_scale(plan):
    data, evals = plan["data"], named(plan["commands"], "eval")
    for seed in SEEDS:
        run = f"{plan['root']}/run-16beams-kitti-hdl64e-s{seed}"
        by_out = {option(w, "--out"): w for w in evals}
        for row, (model, drive_eval, (flag, scale)) in ROWS.items():
            model = model if model.startswith("models/") else f"{run}/{model}"
            scale = scale if scale.startswith("models/") else f"{run}/{scale}"
            drive = by_out[f"{run}/{drive_eval}"]
            assert option(drive, "--data") == f"{data}/drive_labels"
            assert option(drive, "--model") == model and option(drive, flag) == scale, row
            for name in SETS:
                words = by_out[f"{run}/{name}/{row}"]
                assert option(words, "--data") == f"{data}/{name}"
                assert options(words, ("--data", "--out")) == options(drive, ("--data", "--out"))
        assert not [
            out for out in by_out if out.startswith(f"{run}/") and "source_x2_budget_st" in out
        ]


def test_the_direct_row_is_the_shipped_model_at_its_own_scale(plan):
    direct = [w for w in named(plan["commands"], "eval") if option(w, "--out").endswith("direct")]
    # per seed: the drive and two object sets; once for the 64-beam reference
    assert len(direct) == 3 * len(SEEDS) + 3
    for words in direct:
        assert option(words, "--model") == MODEL and option(words, "--scale-from") == MODEL


def test_the_upper_reference_is_the_direct_row_on_the_64_beam_sets(plan):
    reference, data64 = f"{plan['root']}/run-reference", f"{plan['root']}/run-data"
    evals = {option(w, "--out"): w for w in named(plan["commands"], "eval")}
    mine = {out: w for out, w in evals.items() if out.startswith(f"{reference}/")}
    assert set(mine) == {f"{reference}/iter0/eval_direct"} | {
        f"{reference}/{s}/direct" for s in SETS
    }
    assert option(mine[f"{reference}/iter0/eval_direct"], "--data") == f"{data64}/drive_labels"
    for name in SETS:
        assert option(mine[f"{reference}/{name}/direct"], "--data") == f"{data64}/{name}"


def test_the_control_self_trains_the_model_on_its_tracked_labels_with_x2_budget(plan, tmp_path):
    data, commands = plan["data"], plan["commands"]
    run = f"{plan['root']}/run-16beams-kitti-hdl64e-s0"
    by_out = {option(w, "--out"): w for w in commands}
    low = by_out[f"{run}/iter1/pseudo_low"]
    assert option(low, "--model") == MODEL and option(low, "--scale-from") == f"{run}/iter1/ptsn"
    assert option(by_out[f"{run}/iter1/tracked"], "--pseudo") == f"{run}/iter1/pseudo_low"
    control = by_out[f"{run}/baselines/source_x2_budget/model"]
    assert control[0] == "self-train" and option(control, "--init") == MODEL
    assert option(control, "--pseudo") == f"{run}/iter1/tracked"
    # control + tracked ST and x2 + tracked ST: the same self-training, from the control and x2
    control_tst = by_out[f"{run}/baselines/source_x2_budget_tst/model"]
    x2_tst = by_out[f"{run}/iter2_tst/model"]
    assert option(control_tst, "--init") == f"{run}/baselines/source_x2_budget/model"
    assert option(control_tst, "--pseudo") == f"{run}/baselines/source_x2_budget/tracked"
    assert options(control_tst, ("--init", "--pseudo", "--out")) == options(
        x2_tst, ("--init", "--pseudo", "--out")
    )
    # the budget: as many frames as x2's two retrainings (epochs x 2 x |source|), in target epochs
    retrain = sum(float(option(by_out[f"{run}/iter{n}/model"], "--epochs")) for n in (1, 2))
    line = next(
        line for line in plan["lines"] if f"--out {run}/baselines/source_x2_budget/model" in line
    )
    budget = re.search(r"--epochs (\$\(.*\)) --lr", line).group(1)
    for name, frames in (("source", 48), ("target", 1000)):
        (tmp_path / name).mkdir()
        manifest = {"outputs": {"counts": {"frames": frames}}}
        (tmp_path / name / "manifest.json").write_text(json.dumps(manifest))
    budget = budget.replace(f"{run}/data/source", str(tmp_path / "source"))
    budget = budget.replace(f"{data}/target", str(tmp_path / "target"))
    echo = subprocess.run(
        ["bash", "-c", f"echo {budget}"], capture_output=True, text=True, cwd=ROOT
    )
    epochs = echo.stdout
    assert float(epochs) == pytest.approx(retrain * 2 * 48 / 1000)


def test_the_dense_teacher_labels_the_full_scans_and_trains_on_the_thinned_ones(plan):
    """dense_tst: the shipped model's tracked pseudo labels of the 64-beam target (imported and
    registered before any seed's rows), the model self-trained with them on the 16-beam target
    frames (--pseudo-from names the full scans), as long as the other tracked self-trainings."""
    data, dense = plan["data"], f"{plan['root']}/run-data"
    commands = plan["commands"]
    by_out = {option(w, "--out"): w for w in commands}
    order = [option(w, "--out") for w in commands]
    assert option(by_out[f"{dense}/target_poses"], "--data") == f"{dense}/target"
    for seed in SEEDS:
        run = f"{plan['root']}/run-16beams-kitti-hdl64e-s{seed}"
        low = by_out[f"{run}/dense/pseudo_low"]
        assert option(low, "--model") == MODEL and option(low, "--scale-from") == MODEL
        assert option(low, "--data") == f"{dense}/target"
        assert order.index(f"{dense}/target_poses") < order.index(f"{run}/dense/pseudo_low")
        tracked = by_out[f"{run}/dense/tracked"]
        assert option(tracked, "--poses") == f"{dense}/target_poses"
        assert option(tracked, "--data") == f"{dense}/target"
        student = by_out[f"{run}/dense_tst/model"]
        assert student[0] == "self-train" and option(student, "--init") == MODEL
        assert option(student, "--data") == f"{data}/target"
        assert option(student, "--pseudo") == f"{run}/dense/tracked"
        assert option(student, "--pseudo-from") == f"{dense}/target"
        x2_tst = by_out[f"{run}/iter2_tst/model"]
        assert options(student, ("--init", "--pseudo", "--pseudo-from", "--out")) == options(
            x2_tst, ("--init", "--pseudo", "--out")
        )


def test_the_pairs_are_x2_against_the_control_and_with_tracked_st(plan):
    compares = {option(w, "--out") for w in named(plan["commands"], "compare")}
    for seed in SEEDS:
        run = f"{plan['root']}/run-16beams-kitti-hdl64e-s{seed}"
        expected = {f"{run}/compare_real/{name}-{row}.json" for name in ("drive", *SETS)
                    for row in ("x2", "x2_tst", "dense_tst")}  # fmt: skip
        assert {out for out in compares if out.startswith(f"{run}/")} == expected


def test_without_beams_the_plan_of_make_real_kitti_is_unchanged(plan):
    variables = [v for v in plan["variables"] if not v.startswith("REAL_RUN=")]
    variables.append(f"REAL_RUN={plan['root']}/plain")
    unset = make("-n", "real-kitti", *variables)
    at_64 = make("-n", "real-kitti", "BEAMS=64", *variables)
    assert unset.returncode == 0 and unset.stdout == at_64.stdout
    commands = commands_of([line for line in unset.stdout.splitlines() if "/bin/dali " in line])
    assert not any("--beams" in words for words in commands)
    outs = {option(w, "--out") for w in named(commands, "import")}
    assert outs and all(out.startswith(f"{plan['root']}/plain-data/") for out in outs)
    # the control is the pretrained one; no row starts from a shipped model
    control = [w for w in commands if str(option(w, "--out")).endswith("source_x2_budget/model")]
    assert control and all(w[0] == "pretrain" for w in control)
    assert not any(MODEL in " ".join(words) for words in commands)


def test_real_kitti_beams_needs_fewer_than_64_beams():
    for beams in ([], ["BEAMS=64"]):
        result = make("-n", "real-kitti-beams", *beams)
        assert result.returncode != 0 and "BEAMS=32 or 16" in result.stderr
    result = make("-n", "real-kitti", "BEAMS=8")
    assert result.returncode != 0 and "BEAMS must be 64, 32 or 16" in result.stderr


def test_make_real_kitti_at_16_beams_keeps_its_runs_apart(plan):
    """The synthetic-source benchmark on the thinned drives: its own runs, PPCG at 16 beams."""
    variables = [v for v in plan["variables"] if not v.startswith("SEEDS=")]
    commands = commands_of(dali_commands("real-kitti", "BEAMS=16", "SEEDS=0", *variables))
    run = f"{plan['root']}/run-16beams-s0"
    outs = {option(w, "--out"): w for w in commands}
    assert option(outs[f"{run}/iter0/model"], "--source") == f"{run}/data/source"
    assert option(outs[f"{run}/iter1/rc"], "--target-profile") == "kitti-16"
    assert option(outs[f"{run}/iter1/ptsn"], "--data") == f"{plan['data']}/target"


def test_make_models_builds_the_16_beam_model_from_its_row_and_gates_it(plan):
    """`make models` goes on to models/kitti-16beam: the row SPARSE_MODELS_ROW (dense_tst) of the
    beams task's runs on every seed, the card from seed 0 with the row over the seeds, its test
    frame imported at 16 beams, and the gate against the 16-beam model shipped, or before one
    ships, against direct transfer on the same 16-beam sets."""
    variables = [v for v in plan["variables"] if not v.startswith("SEEDS=")]
    lines = make("-n", "models", *variables, "SEEDS=0 1").stdout.splitlines()
    commands = commands_of([line for line in lines if "/bin/dali " in line])
    data, by_out = plan["data"], {}
    for words in commands:
        by_out.setdefault(option(words, "--out"), words)
    for seed in SEEDS:
        run = f"{plan['root']}/run-16beams-kitti-hdl64e-s{seed}"
        assert by_out[f"{run}/dense_tst/model"][0] == "self-train"
        assert option(by_out[f"{run}/dense_tst/eval"], "--data") == f"{data}/drive_labels"
        # the recipe alone: no other row of the task is built for the model
        assert f"{run}/iter2/model" not in by_out and f"{run}/iter1/ptsn" not in by_out
    fixture = by_out[f"{data}/fixture"]
    assert option(fixture, "--beams") == "16" and fixture[:2] == ["import", "kitti"]
    run0 = f"{plan['root']}/run-16beams-kitti-hdl64e-s0"
    joined = "\n".join(lines).replace("\\\n", " ").splitlines()  # continuation lines joined
    gate = next(line for line in joined if "model_gate.py" in line and f"--out {run0}/" in line)
    shipped = "models/kitti-16beam" if (ROOT / "models/kitti-16beam/model.pt").is_file() else MODEL
    assert re.search(r"--shipped (\S+)", gate).group(1) == shipped
    assert (shipped == MODEL) == ("direct transfer" in gate)
    assert f"--set drive={data}/drive_labels" in gate
    card = next(line for line in joined if "model_card.py" in line and "kitti-16beam" in line)
    assert re.search(r"--model (\S+)", card).group(1) == f"{run0}/dense_tst/model"
    assert re.search(r"--out (\S+)", card).group(1) == "models/kitti-16beam"
    assert f"--scale-from {MODEL}" in card and "--name kitti-16beam" in card
    assert f"--gate {run0}/model_gate.json" in card
    recipe = re.search(r"--recipe drive=(\S+)", card).group(1).split(",")
    assert recipe == [f"{plan['root']}/run-16beams-kitti-hdl64e-s{s}/dense_tst/eval" for s in SEEDS]


def test_models_beams_needs_fewer_than_64_beams():
    result = make("-n", "models-beams")
    assert result.returncode != 0 and "BEAMS=32 or 16" in result.stderr
