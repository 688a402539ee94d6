"""`make real-kitti`'s plan (`make -n`, nothing trains) over several drives and seeds: every drive
imported unlabeled and merged into one target, the DALI stages and the controls adapting to it,
every row evaluated on the labelled drive and on the object frames split by their drive, control +
ST self-trained exactly like x2 + ST, the source trainings the same commands as the plain per-run
targets (so runs built that way are reused), and the object frames' split run for real."""

from __future__ import annotations

import shlex
import shutil
from pathlib import Path

import pytest
from make_plans import dali_commands, make, named, option, options, values

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")

LABELLED = "data/raw/2011_09_26/2011_09_26_drive_0001_sync"
RAW = "data/scans/2011_09_26/2011_09_26_drive_0005_sync"
SEEDS = ("0", "1")
# the object frames' raw drives: 0005 and odometry 04's (2011_09_30_drive_0016) are in the target
TABLE = [
    ("000001", "2011_09_26_drive_0005_sync"),
    ("000002", "2011_09_26_drive_0101_sync"),
    ("000003", "2011_09_30_drive_0016_sync"),
    ("000004", "2011_10_03_drive_0047_sync"),
]
ROWS = {  # row -> (model, drive evaluation)
    "source": ("iter0/model", "iter0/eval"),
    "ptsn": ("iter0/model", "iter0/eval_ptsn"),
    "x1": ("iter1/model", "iter1/eval"),
    "x2": ("iter2/model", "iter2/eval"),
    "x2_st": ("iter2_st/model", "iter2_st/eval"),
    "control": ("baselines/source_x2_budget/model", "baselines/source_x2_budget/eval_ptsn"),
    "control_st": ("baselines/source_x2_budget_st/model", "baselines/source_x2_budget_st/eval"),
    "x2_tst": ("iter2_tst/model", "iter2_tst/eval"),
    "control_tst": ("baselines/source_x2_budget_tst/model", "baselines/source_x2_budget_tst/eval"),
    "control_tst2": (
        "baselines/source_x2_budget_tst2/model",
        "baselines/source_x2_budget_tst2/eval",
    ),
    "oracle": ("baselines/sim_oracle_x2_budget/model", "baselines/sim_oracle_x2_budget/eval"),
}
PAIRS = (("x2", "control"), ("x2_st", "control_st"), ("x2_tst", "control_tst"))
SOURCE_TRAININGS = (
    "data/source",
    "data/target",
    "iter0/model",
    "baselines/source_x2_budget/model",
    "baselines/sim_oracle_x2_budget/model",
)


@pytest.fixture(scope="module")
def setup(tmp_path_factory) -> dict:
    """Object frames with a frames table, odometry sequences 00 (no calib) and 04 (calib)."""
    root = tmp_path_factory.mktemp("real")
    (root / "kitti" / "training").mkdir(parents=True)
    lines = ["id\traw_drive\traw_frame\tcars\tpoints"]
    lines += [f"{frame}\t{drive}\t0\t1\t100" for frame, drive in TABLE]
    (root / "kitti" / "frames.tsv").write_text("\n".join(lines) + "\n")
    for sequence in ("00", "04"):
        (root / "odometry" / "sequences" / sequence / "velodyne").mkdir(parents=True)
    (root / "odometry" / "sequences" / "04" / "calib.txt").write_text("P2: 0\n")
    drives = [LABELLED, RAW, f"{root}/odometry/sequences/00", f"{root}/odometry/sequences/04/"]
    variables = [
        f"REAL_RUN={root / 'run'}",
        f"REAL_DRIVE={LABELLED}",
        f"REAL_DRIVES={' '.join(drives)}",
        f"REAL_OBJECTS={root / 'kitti' / 'training'}",
        f"SEEDS={' '.join(SEEDS)}",
    ]
    data = root / "run-data"
    commands = [
        shlex.split(line.split("/bin/dali ", 1)[1])
        for line in dali_commands("real-kitti", *variables)
    ]
    return {
        "root": root,
        "data": data,
        "run": root / "run",
        "variables": variables,
        "commands": commands,
    }


def by_out(commands, *verb: str) -> dict[str, list[str]]:
    """The `verb` commands keyed by their --out."""
    return {option(w, "--out"): w for w in named(commands, *verb)}


def assert_self_trained_like(mine: list[str], theirs: list[str], init: str, pseudo: str):
    """`mine` fine-tunes `init` on `pseudo` with the budget and flags of `theirs`."""
    assert option(mine, "--init") == init
    assert option(mine, "--pseudo") == pseudo
    skip = ("--init", "--pseudo", "--out")
    assert options(mine, skip) == options(theirs, skip)


def test_every_drive_is_imported_unlabeled_and_merged_into_the_target(setup):
    data, commands = setup["data"], setup["commands"]
    imports = {
        option(w, "--out"): w for w in named(commands, "import") if "/drives/" in option(w, "--out")
    }
    raw = {f"{data}/drives/2011_09_26_drive_0001", f"{data}/drives/2011_09_26_drive_0005"}
    odometry = {f"{data}/drives/odometry_00", f"{data}/drives/odometry_04"}
    assert set(imports) == raw | odometry
    for out in raw:
        assert imports[out][:2] == ["import", "kitti-raw"]
        assert "--no-labels" in imports[out] and "--crop-fov" in imports[out]
    # camera field of view everywhere: through the calib where there is one, else by azimuth
    assert "--crop-fov" in imports[f"{data}/drives/odometry_04"]
    assert option(imports[f"{data}/drives/odometry_00"], "--crop-front-deg") == "82"
    assert "--crop-fov" not in imports[f"{data}/drives/odometry_00"]
    merges = [w for w in named(commands, "merge") if option(w, "--out") == f"{data}/target"]
    assert merges and all(w == merges[0] for w in merges)
    inputs = values(merges[0], "--in")
    assert (
        inputs == [f"{Path(out).name}={out}" for out in sorted(imports)]
        and "--no-labels" in merges[0]
    )


def test_the_dali_stages_and_the_controls_adapt_to_the_merged_target(setup):
    data, commands = setup["data"], setup["commands"]
    adapting = [
        w
        for w in commands
        if w[0] in ("ptsn-sweep", "pseudo-label", "ppcg-rc", "ppcg-cf", "self-train")
    ]
    assert adapting
    assert all(option(w, "--data") == f"{data}/target" for w in adapting)
    # only the evaluations, the comparisons and the merge that names the drive's frames read labels
    for words in commands:
        if any(
            "drive_labels" in word or "/objects" in word or "drive_tracklets" in word
            for word in words
        ):
            assert words[0] in ("eval", "compare", "merge", "import"), words
    labelled = named(commands, "import", "kitti-raw")
    assert {option(w, "--out") for w in labelled if "--no-labels" not in w} == {
        f"{data}/drive_tracklets"
    }


def test_every_row_is_evaluated_on_every_set_in_every_seed(setup):
    data, commands = setup["data"], setup["commands"]
    evals = named(commands, "eval")
    assert all("--protocol" in w and option(w, "--protocol") == "kitti" for w in evals)
    assert all(" ".join(w).count("--iou") == 2 for w in evals)
    for seed in SEEDS:
        run = f"{setup['run']}-s{seed}"
        on_drive = {
            option(w, "--out"): w for w in evals if option(w, "--data") == f"{data}/drive_labels"
        }
        for row, (model, drive_eval) in ROWS.items():
            drive = on_drive[f"{run}/{drive_eval}"]
            assert option(drive, "--model") == f"{run}/{model}"
            scale = options(drive, ("--data", "--out"))
            for set_name in ("objects_adapted", "objects_other"):
                on_set = [w for w in evals if option(w, "--out") == f"{run}/{set_name}/{row}"]
                assert len({" ".join(w) for w in on_set}) == 1, (row, set_name)
                assert option(on_set[0], "--data") == f"{data}/{set_name}"
                # the same model at the same scale as on the drive
                assert options(on_set[0], ("--data", "--out")) == scale


def test_control_st_is_pseudo_labelled_and_self_trained_like_x2_st(setup):
    commands = setup["commands"]
    run = f"{setup['run']}-s0"
    pseudo = by_out(commands, "pseudo-label")
    x2, control = pseudo[f"{run}/iter3/pseudo"], pseudo[f"{run}/baselines/source_x2_budget/pseudo"]
    assert option(control, "--model") == f"{run}/baselines/source_x2_budget/model"
    assert option(control, "--scale-from") == f"{run}/baselines/source_x2_budget/ptsn"
    skip = ("--model", "--scale-from", "--out")
    assert options(control, skip) == options(x2, skip)
    train = by_out(commands, "self-train")
    x2_st = train[f"{run}/iter2_st/model"]
    control_st = train[f"{run}/baselines/source_x2_budget_st/model"]
    baseline = f"{run}/baselines/source_x2_budget"
    assert_self_trained_like(control_st, x2_st, f"{baseline}/model", f"{baseline}/pseudo")
    assert option(control_st, "--epochs") == option(x2_st, "--epochs") is not None


def test_tracked_rows_self_train_like_st_on_labels_tracked_over_registered_scans(setup):
    data, commands = setup["data"], setup["commands"]
    registers = [w for w in named(commands, "register")]
    # one registration of the target, shared by every seed and row
    assert registers and all(w == registers[0] for w in registers)
    assert option(registers[0], "--data") == f"{data}/target"
    poses = option(registers[0], "--out")
    for seed in SEEDS:
        run = f"{setup['run']}-s{seed}"
        pseudo = by_out(commands, "pseudo-label")
        tracks = by_out(commands, "track-pseudo")
        train = by_out(commands, "self-train")
        for labels, row, plain in (
            ("iter3", "iter2_tst", "iter2_st"),
            ("baselines/source_x2_budget", "baselines/source_x2_budget_tst",
             "baselines/source_x2_budget_st"),
        ):  # fmt: skip
            low, cut = pseudo[f"{run}/{labels}/pseudo_low"], pseudo[f"{run}/{labels}/pseudo"]
            # the same model and scale as the plain row's labels, a lower cut for the tracks
            assert options(low, ("--score-min", "--out")) == options(cut, ("--score-min", "--out"))
            assert float(option(low, "--score-min")) < float(option(cut, "--score-min"))
            tracked = tracks[f"{run}/{labels}/tracked"]
            assert option(tracked, "--pseudo") == f"{run}/{labels}/pseudo_low"
            assert option(tracked, "--data") == f"{data}/target"
            assert option(tracked, "--poses") == poses
            mine, theirs = train[f"{run}/{row}/model"], train[f"{run}/{plain}/model"]
            assert option(mine, "--pseudo") == f"{run}/{labels}/tracked"
            assert options(mine, ("--pseudo", "--out")) == options(theirs, ("--pseudo", "--out"))


def test_the_second_tracked_round_relabels_with_the_first_at_its_own_scale(setup):
    commands = setup["commands"]
    for seed in SEEDS:
        run = f"{setup['run']}-s{seed}"
        first, second = (
            f"{run}/baselines/source_x2_budget_tst",
            f"{run}/baselines/source_x2_budget_tst2",
        )
        sweeps = by_out(commands, "ptsn-sweep")
        assert option(sweeps[f"{first}/ptsn"], "--model") == f"{first}/model"
        low = by_out(commands, "pseudo-label")[f"{first}/pseudo_low"]
        assert option(low, "--model") == f"{first}/model"
        assert option(low, "--scale-from") == f"{first}/ptsn"
        tracked = by_out(commands, "track-pseudo")[f"{first}/tracked"]
        assert option(tracked, "--pseudo") == f"{first}/pseudo_low"
        train = by_out(commands, "self-train")
        mine, theirs = train[f"{second}/model"], train[f"{first}/model"]
        # the same self-training budget and flags as the first round
        assert_self_trained_like(mine, theirs, f"{first}/model", f"{first}/tracked")
        evals = by_out(commands, "eval")
        assert option(evals[f"{second}/eval"], "--scale-from") == f"{first}/ptsn"


def test_make_models_builds_the_recipe_row_on_every_seed(setup):
    """`make models SEEDS=...`: the shipped seed's whole chain and, on every other seed, the
    recipe row's evaluations (not the benchmark's other rows)."""
    variables = [v for v in setup["variables"] if not v.startswith("SEEDS=")]
    commands = [
        shlex.split(line.split("/bin/dali ", 1)[1])
        for line in dali_commands("models", *variables, "SEEDS=0 1 2")
        if "/bin/dali " in line  # not the cards' summaries that name dali commands
    ]
    outs = {option(w, "--out") for w in commands}
    for seed in SEEDS + ("2",):
        run = f"{setup['run']}-s{seed}"
        assert f"{run}/baselines/source_x2_budget_tst2/eval" in outs  # control + tracked ST x2
        assert f"{run}/objects_other/control_tst2" in outs
        assert f"{run}/iter2/model" not in outs  # DALI's rows are not the recipe
    assert f"{setup['run']}-s3/baselines/source_x2_budget_tst2/eval" not in outs


def test_make_models_replaces_neither_model_before_the_gate_passes(setup):
    """The gate judges the adapted model before either card is written: a refused model leaves
    models/waymo-like-source as well as models/kitti-hdl64e as they were (the adapted model's
    card names the source it came from)."""
    variables = [v for v in setup["variables"] if not v.startswith("SEEDS=")]
    lines = make("-n", "models", *variables, "SEEDS=0", "MODELS_BEAMS=").stdout
    lines = lines.replace("\\\n", " ").splitlines()  # continuation lines joined
    gate = next(i for i, line in enumerate(lines) if "model_gate.py" in line)
    cards = [i for i, line in enumerate(lines) if "model_card.py" in line]
    outs = [line.split("--out ")[-1].split()[0] for line in lines if "model_card.py" in line]
    assert outs == ["models/waymo-like-source", "models/kitti-hdl64e"]
    assert gate < min(cards)


def test_the_pairs_are_compared_on_every_set_with_a_paired_bootstrap(setup):
    data, commands = setup["data"], setup["commands"]
    compares = by_out(commands, "compare")
    truth = {"drive": f"{data}/drive_labels", "objects_adapted": f"{data}/objects_adapted",
             "objects_other": f"{data}/objects_other"}  # fmt: skip
    for seed in SEEDS:
        run = f"{setup['run']}-s{seed}"
        for set_name, gt in truth.items():
            for row, reference in PAIRS:
                words = compares[f"{run}/compare_real/{set_name}-{row}.json"]
                assert option(words, "--gt") == gt and option(words, "--seed") == seed
                preds = values(words, "--pred")
                directory = [
                    f"{run}/{ROWS[name][1]}" if set_name == "drive" else f"{run}/{set_name}/{name}"
                    for name in (reference, row)
                ]
                assert preds == [
                    f"{name}={d}/predictions.parquet"
                    for name, d in zip((reference, row), directory, strict=True)
                ]


def test_the_source_trainings_are_the_plain_run_targets(setup):
    """The same commands as `make RUN=REAL_RUN-s<seed> SEED=<seed> FRAMES=48 EPOCHS=6 <targets>`:
    runs started that way are the ones `make real-kitti` continues."""
    for seed in SEEDS:
        run = f"{setup['run']}-s{seed}"
        targets = [f"{run}/{path}/manifest.json" for path in SOURCE_TRAININGS]
        plain = dali_commands(
            f"RUN={run}",
            f"SEED={seed}",
            "FRAMES=48",
            "EPOCHS=6",
            "TRAIN_FLAGS=--threads=1",
            *targets,
        )
        assert len(plain) == len(SOURCE_TRAININGS)
        real = dali_commands("real-kitti", "TRAIN_FLAGS=--threads=1", *setup["variables"])
        for line in plain:
            assert line in real, line


def test_the_object_frames_are_split_by_their_drive(setup):
    data = setup["data"]
    goals = [f"{data}/objects_adapted.txt", f"{data}/objects_other.txt"]
    result = make(*goals, *setup["variables"])
    assert result.returncode == 0, result.stderr
    adapted = (data / "objects_adapted.txt").read_text().split()
    other = (data / "objects_other.txt").read_text().split()
    assert adapted == ["000001", "000003"] and other == ["000002", "000004"]
    imports = by_out(setup["commands"], "import", "kitti")
    for set_name in ("objects_adapted", "objects_other"):
        words = imports[f"{data}/{set_name}"]
        assert option(words, "--ids") == f"{data}/{set_name}.txt" and "--crop-fov" in words


def test_without_a_frames_table_all_object_frames_are_one_set(tmp_path):
    commands = dali_commands("real-kitti", f"REAL_RUN={tmp_path / 'run'}", f"REAL_DRIVE={LABELLED}",
                             f"REAL_OBJECTS={tmp_path}")  # fmt: skip
    outs = {option(shlex.split(line.split("/bin/dali ", 1)[1]), "--out") for line in commands}
    assert f"{tmp_path}/run-data/objects" in outs
    assert not any("objects_" in out for out in outs if out)


def test_the_holdout_adapts_on_every_drive_but_the_labelled_one(setup):
    """`make real-kitti-holdout`: the rows of `make real-kitti` in runs of their own, adapted on
    REAL_DRIVES without REAL_DRIVE (named with or without a trailing slash), still judged on
    REAL_DRIVE's tracklets; the object frames of that drive's raw drive count as another drive's."""
    root = setup["root"]
    variables = [v for v in setup["variables"] if not v.startswith("REAL_DRIVES=")]
    drives = [f"{LABELLED}/", RAW, f"{root}/odometry/sequences/04/"]
    variables.append(f"REAL_DRIVES={' '.join(drives)}")
    commands = [shlex.split(line.split("/bin/dali ", 1)[1])
                for line in dali_commands("real-kitti-holdout", *variables)]  # fmt: skip
    data = f"{root}/run-holdout-data"
    merges = {option(w, "--out"): w for w in named(commands, "merge")}
    assert values(merges[f"{data}/target"], "--in") == [
        f"2011_09_26_drive_0005={data}/drives/2011_09_26_drive_0005",
        f"odometry_04={data}/drives/odometry_04",
    ]
    imports = {option(w, "--out"): w for w in named(commands, "import")}
    assert imports[f"{data}/drive_tracklets"][:3] == ["import", "kitti-raw", LABELLED]
    assert not any("2011_09_26_drive_0001" in out for out in imports if "/drives/" in out)
    evals = [w for w in named(commands, "eval") if option(w, "--out").endswith("/iter2/eval")]
    assert {option(w, "--data") for w in evals} == {f"{data}/drive_labels"}
    assert {option(w, "--out") for w in evals} == {
        f"{root}/run-holdout-s{seed}/iter2/eval" for seed in SEEDS
    }
    # the object frames split by the drives adapted on: 0001's raw drive is not among them
    plan = make("-n", "real-kitti-holdout", *variables).stdout
    split = [line for line in plan.splitlines() if "awk" in line and "objects_adapted" in line]
    assert split and all(
        "drives=' 2011_09_26_drive_0005_sync 2011_09_30_drive_0016_sync '" in line for line in split
    )
    result = make("-n", "real-kitti-holdout", *variables[:-1], f"REAL_DRIVES={RAW}")
    assert result.returncode != 0 and "REAL_DRIVES must hold REAL_DRIVE" in result.stderr


def pseudo_diagnostic(plan: str, seed: str) -> list[str] | None:
    """The pseudo-label directories `bench/pseudo_labels.py` measures for one seed's run in a plan
    (None: it does not run there)."""
    for line in plan.replace("\\\n", " ").splitlines():
        words = shlex.split(line)
        if "bench/pseudo_labels.py" not in words or "--pseudo" not in words:
            continue
        after = words[words.index("--pseudo") + 1 :]
        dirs = after[: next((i for i, w in enumerate(after) if w.startswith("--")), len(after))]
        if all(f"-s{seed}/" in path for path in dirs):
            return dirs
    return None


def test_fewer_rows_build_no_other_row_for_the_diagnostics(setup):
    """The pseudo-label diagnostic measures the labels of the rows built, and the paired
    comparisons pair rows built: fewer REAL_ROW_NAMES build no DALI iteration for either."""
    run = f"{setup['run']}-s0"
    everything = pseudo_diagnostic(make("-n", "real-kitti", *setup["variables"]).stdout, "0")
    assert everything == [
        f"{run}/{path}"
        for path in ("iter1/pseudo", "iter2/pseudo", "iter3/pseudo",
                     "baselines/source_x2_budget/pseudo", "iter3/tracked",
                     "baselines/source_x2_budget/tracked")
    ]  # fmt: skip
    recipe = [*setup["variables"], "REAL_ROW_NAMES=control control_tst control_tst2"]
    result = make("-n", "real-kitti", *recipe)
    assert result.returncode == 0, result.stderr  # no comparison with a row it does not build
    plan = result.stdout
    assert pseudo_diagnostic(plan, "0") == [f"{run}/baselines/source_x2_budget/tracked"]
    outs = {option(shlex.split(line.split("/bin/dali ", 1)[1]), "--out")
            for line in plan.splitlines() if "/bin/dali " in line}  # fmt: skip
    assert not any("/iter1/" in out or "/iter3/" in out for out in outs if out)
    plan = make("-n", "real-kitti", *setup["variables"], "REAL_ROW_NAMES=source control").stdout
    assert pseudo_diagnostic(plan, "0") is None
