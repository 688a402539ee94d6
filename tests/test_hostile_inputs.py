"""Fuzz table: every command's numeric options and every kind of input file, fed hostile values
(NaN, inf, negative, zero, huge, wrong type, truncated, non-UTF-8, a directory instead of a file),
and every kind of output path pointed at something dali does not own. Each case must end with
exit code 1 or 2, a one-line message and no traceback, no output written, and every file outside
the output unchanged (docs/input-validation.md, docs/data-safety.md).

The table is seeded and fixed; inputs are tiny (two toy frames, a detector trained for one epoch,
a two-car procedural library). Option cases fail while click parses, before any work.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from test_malformed_inputs import make_world

from dali_cli.cli import main
from dali_cli.store.artifacts import BoxTable, read_boxes, write_boxes

ROOT = Path(__file__).resolve().parents[1]

FIXTURES = Path(__file__).resolve().parent / "fixtures" / "real"
KITTI_ROOT = FIXTURES / "kitti"

# hostile spellings of a number, by what the option accepts (every one must be refused)
POSITIVE_BAD = ("nan", "inf", "-inf", "-1", "0", "1e999", "x", "")
NON_NEGATIVE_BAD = ("nan", "inf", "-1", "1e999", "x")
FRACTION_BAD = ("nan", "inf", "-0.5", "1.5", "x")
COUNT_BAD = ("0", "-1", "1.5", "nan", "x", "1000000000")
SEED_BAD = ("-1", "1.5", "x", "99999999999999999999")
SIZE_BAD = ("nan,1,1", "0,0,0", "-4,1,1", "inf,1,1", "1,1", "a,b,c", "1,1,1,1")
DELTA_BAD = ("nan,0,0", "inf,0,0", "-inf,0,0", "1,2", "x,0,0")
RANGE_BAD = ("1,0.5", "nan,1", "1,inf", "0,1", "1", "1,1")


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Valid inputs (test_malformed_inputs.make_world) and a KITTI root."""
    root = make_world(tmp_path_factory.mktemp("hostile"))
    shutil.copytree(KITTI_ROOT, root / "kitti")
    return root


def tree_hashes(root: Path) -> dict[str, str]:
    """Every path under `root` with a digest of its content (directories and links marked)."""
    hashes = {}
    for path in sorted(root.rglob("*")):
        key = str(path.relative_to(root))
        if path.is_symlink():
            hashes[key] = "link:" + str(path.readlink())
        elif path.is_file():
            hashes[key] = hashlib.blake2b(path.read_bytes(), digest_size=16).hexdigest()
        else:
            hashes[key] = "dir"
    return hashes


def write_or_mkdir(path: Path, content: bytes | None) -> None:
    """`content` into the file `path`; None: a directory where the file should be."""
    if content is None:
        path.mkdir()
    else:
        path.write_bytes(content)


def expect_refused(root: Path, args: list, out: Path | None = None, *needles: str) -> str:
    """Run `dali args...` in-process: exit 1 or 2 with a message, no traceback, nothing under
    `root` changed (the output included: it must not appear). Returns the output."""
    before = tree_hashes(root)
    result = invoke(*args)
    assert result.exit_code in (1, 2), (args, result.exit_code, result.output)
    assert isinstance(result.exception, SystemExit), (
        f"traceback instead of an error message for {args}: {result.exception!r}\n{result.output}"
    )
    assert "Traceback" not in result.output
    assert result.output.strip(), "no message"
    for needle in needles:
        assert needle in result.output, (needle, result.output)
    assert tree_hashes(root) == before, f"something was written or changed: {args}"
    if out is not None:
        assert not out.exists()
    return result.output


# ---------------------------------------------------------------------------------------------
# numeric options: refused while click parses (exit 2), naming the option


def option_cases():
    """(command, option, value) for every numeric option of every command."""
    table = {
        "pseudo-label": {"--scale": POSITIVE_BAD,
                         "--nms-iou": FRACTION_BAD, "--batch-size": COUNT_BAD},
        "ptsn-sweep": {"--frame-fraction": FRACTION_BAD + ("0",),
                       "--subsample-fraction": FRACTION_BAD, "--noise": NON_NEGATIVE_BAD,
                       "--frames": COUNT_BAD[:-1]},
        "pretrain": {"--target-size": SIZE_BAD, "--ros-range": RANGE_BAD,
                     "--minutes": POSITIVE_BAD, "--lr": POSITIVE_BAD, "--epochs": POSITIVE_BAD,
                     "--batch-size": COUNT_BAD, "--seed": SEED_BAD, "--threads": COUNT_BAD},
        "retrain": {"--target-size": SIZE_BAD, "--lr": POSITIVE_BAD, "--minutes": POSITIVE_BAD},
        "size-norm": {"--delta": DELTA_BAD},
        "view": {"--range-m": POSITIVE_BAD, "--score-min": FRACTION_BAD,
                 "--width-px": COUNT_BAD},
        "ppcg-rc": {"--point-margin-m": NON_NEGATIVE_BAD, "--ground-margin-m": NON_NEGATIVE_BAD},
        "export-openpcdet": {"--score-min": FRACTION_BAD},
        "eval": {"--scale": POSITIVE_BAD, "--iou": FRACTION_BAD,
                 "--score-min": FRACTION_BAD},
        "synth": {"--frames": COUNT_BAD[:-1], "--seed": SEED_BAD, "--threads": COUNT_BAD},
        "library-build": {"--length-m": ("0:inf", "nan:5", "5:1", "-1:5", "x")},
        "import-kitti": {"--intensity-max": POSITIVE_BAD},
    }  # fmt: skip
    return [
        (command, option, value)
        for command, options in table.items()
        for option, values in options.items()
        for value in values
    ]


def base_args(world: Path, command: str, out: Path) -> list:
    """A valid invocation of `command` writing `out` (the hostile option is appended)."""
    model, target, source = world / "model", world / "target", world / "source"
    return {
        "pseudo-label": ["pseudo-label", "--model", model, "--data", target, "--out", out],
        "ptsn-sweep": ["ptsn-sweep", "--model", model, "--data", target, "--out", out],
        "pretrain": ["pretrain", "--source", source, "--out", out, "--size-norm", "sn"],
        "retrain": ["retrain", "--init", model, "--source", source, "--ppcg", target,
                    "--out", out, "--size-norm", "sn"],
        "size-norm": ["size-norm", "--data", target, "--out", out],
        "view": ["view", target, "--frame", "0", "--out", out],
        "ppcg-rc": ["ppcg-rc", "--data", target, "--boxes", target, "--library",
                    world / "library", "--out", out],
        "export-openpcdet": ["export", "openpcdet", target, "--out", out],
        "eval": ["eval", "--pred", target, "--gt", target, "--out", out],
        "synth": ["synth", "--sensor", "kitti", "--out", out],
        "library-build": ["library", "build", "--procedural", "1", "--out", out],
        "import-kitti": ["import", "kitti", world / "kitti", "--out", out],
    }[command]  # fmt: skip


@pytest.mark.parametrize("command, option, value", option_cases())
def test_a_hostile_number_is_refused_naming_the_option(world, tmp_path, command, option, value):
    out = tmp_path / ("out.png" if command == "view" else "out")
    args = [*base_args(world, command, out), option, value]
    if command == "synth" and option != "--frames":
        args += ["--frames", "1"]
    expect_refused(world, args, out, option)
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------------------------
# values that parse but make no sense, and sizes the machine cannot hold: exit 1, nothing written


def test_frame_and_ray_counts_beyond_the_limits_are_refused_before_allocating(world, tmp_path):
    out = tmp_path / "out"
    expect_refused(
        tmp_path, ["synth", "--sensor", "kitti", "--frames", 10**12, "--out", out], out,
        "--frames", "DALI_MAX_FRAMES",
    )  # fmt: skip
    sensors = tmp_path / "sensors.toml"
    sensors.write_text(
        "[big]\nbeams = 100000000\npoints_per_beam = 2000\nmount_height_m = 1.7\n"
        "max_range_m = 100.0\nelevation_min_deg = -20.0\nelevation_max_deg = 5.0\n"
        "car_mean_lwh_m = [4.0, 1.8, 1.5]\n"
    )
    expect_refused(
        tmp_path, ["synth", "--sensor", "big", "--sensors", sensors, "--frames", 1, "--out", out],
        out, "beams", "DALI_MAX_RAYS_PER_FRAME",
    )  # fmt: skip


def test_a_huge_sparse_point_file_is_refused_before_it_is_read(world, tmp_path):
    root = tmp_path / "kitti"
    shutil.copytree(world / "kitti", root)
    scan = next((root / "training" / "velodyne").glob("*.bin"))
    with open(scan, "r+b") as file:
        file.truncate(2 * 2**30)  # 2 GB of zeros, sparse: no disk used
    out = tmp_path / "out"
    expect_refused(tmp_path, ["import", "kitti", root, "--out", out], out, scan.name,
                   "DALI_MAX_POINT_FILE_BYTES")  # fmt: skip


def kitti_with_label(world: Path, case: Path, edit) -> Path:
    """A copy of the KITTI root whose first label file's first line is edited by `edit`."""
    root = case / "kitti"
    shutil.copytree(world / "kitti", root)
    label = sorted((root / "training" / "label_2").glob("*.txt"))[0]
    lines = label.read_text().splitlines()
    edit(label, lines)
    return root


@pytest.mark.parametrize(
    "how",
    ["z-1e9", "l-1e30", "non-utf8", "directory", "truncated-line", "nan-field"],
)
def test_hostile_kitti_labels_are_refused(world, tmp_path, how):
    def edit(label: Path, lines: list[str]) -> None:
        fields = lines[0].split()
        if how == "z-1e9":
            fields[13] = "1e9"
        elif how == "l-1e30":
            fields[10] = "1e30"
        elif how == "nan-field":
            fields[11] = "nan"
        elif how == "truncated-line":
            fields = fields[:7]
        if how == "non-utf8":
            label.write_bytes(b"Car \xff\xfe 0 0\n")
        elif how == "directory":
            label.unlink()
            label.mkdir()
        else:
            label.write_text("\n".join([" ".join(fields), *lines[1:]]) + "\n")

    root = kitti_with_label(world, tmp_path, edit)
    out = tmp_path / "out"
    expect_refused(tmp_path, ["import", "kitti", root, "--out", out], out, "label_2")


def boxes_with(world: Path, case: Path, column: int, value: float) -> Path:
    """A box table of the target's labels with row 0's `column` set to `value`."""
    table = read_boxes(world / "target")
    boxes = table.boxes.copy()
    boxes[0, column] = value
    directory = case / "boxes"
    directory.mkdir()
    write_boxes(directory, BoxTable.from_arrays(table.frame_id, boxes, label=table["label"]))
    return directory


def test_implausible_boxes_are_refused_by_every_stage_that_reads_them(world, tmp_path):
    """One plausibility rule: boxes 10^6 m away (ppcg-rc), l = 1e30 (eval), as pretrain."""
    far = boxes_with(world, tmp_path, 0, 1e6)
    out = tmp_path / "out"
    args = ["ppcg-rc", "--data", world / "target", "--boxes", far, "--library",
            world / "library", "--out", out, "--no-progress"]  # fmt: skip
    expect_refused(tmp_path, args, out, "row 0", "centre")
    (far / "boxes.parquet").unlink()
    far.rmdir()
    long = boxes_with(world, tmp_path, 3, 1e30)
    for args in (
        ["eval", "--pred", long, "--gt", world / "target", "--out", tmp_path / "m.json"],
        ["eval", "--pred", world / "target", "--gt", long],
        ["pretrain", "--source", world / "source", "--boxes", long, "--out", out],
    ):
        expect_refused(tmp_path, args, tmp_path / "m.json", "row 0", "'l'")


@pytest.mark.parametrize("value", ["nan", "-50"])
def test_a_nonsense_mount_height_is_refused_not_a_silent_empty_result(world, tmp_path, value):
    """The mount height that scales the target comes from its sensor profile: a profile with a
    NaN or negative one is refused by the stages that scale, before any work."""
    sensors = tmp_path / "sensors.toml"
    sensors.write_text(
        (ROOT / "sensors.toml")
        .read_text()
        .replace("mount_height_m = 1.73", f"mount_height_m = {value}", 1)
    )
    assert f"mount_height_m = {value}" in sensors.read_text()
    for command in ("pseudo-label", "ptsn-sweep"):
        out = tmp_path / command
        args = [*base_args(world, command, out), "--sensors", sensors, "--target-profile", "kitti"]
        args += ["--scale", "1.0"] if command == "pseudo-label" else []
        expect_refused(world, args, out, "mount_height_m")


# ---------------------------------------------------------------------------------------------
# hostile input files: manifests, model cards, detector configs, resume states


MANIFESTS = {
    "list": b"[1, 2]",
    "string": b'"x"',
    "non-utf8": b"\xff\xfe\x00{",
    "truncated": b'{"stage": "pseudo-label", "inp',
    "inputs-not-records": b'{"inputs": {"target": 5}}',
    "records-not-objects": b'{"inputs": {"target": [1, 2]}}',
}


@pytest.mark.parametrize("how", [*MANIFESTS, "directory"])
def test_a_hostile_input_manifest_is_refused_naming_it(world, tmp_path, how):
    boxes = boxes_with(world, tmp_path, 0, float(read_boxes(world / "target").boxes[0, 0]))
    write_or_mkdir(boxes / "manifest.json", MANIFESTS.get(how))
    out = tmp_path / "out"
    args = ["ppcg-rc", "--data", world / "target", "--boxes", boxes, "--library",
            world / "library", "--out", out, "--no-progress"]  # fmt: skip
    expect_refused(tmp_path, args, out, "manifest.json")


MODEL_CONFIGS = {
    "pfn-1e308": {"pfn_channels": 1e308},
    "pfn-string": {"pfn_channels": "32"},
    "pfn-huge-int": {"pfn_channels": 10**400},
    "pillar-nan": {"pillar_m": math.nan},
    "pillar-zero": {"pillar_m": 0},
    "range-reversed": {"x_range_m": [70.4, 0.0]},
    "grid-32tb": {"pillar_m": 0.001, "x_range_m": [0.0, 9000.0], "y_range_m": [-9000, 9000]},
    "channels-huge": {"block_channels": [4096, 4096, 4096], "pillar_m": 0.01},
}


@pytest.mark.parametrize("how", [*MODEL_CONFIGS, "5000-digits", "not-json", "directory"])
def test_a_hostile_model_card_is_refused_naming_the_field(world, tmp_path, how):
    model = tmp_path / "model"
    shutil.copytree(world / "model", model)
    card = model / "model.json"
    document = json.loads(card.read_text())
    needle = "model.json"
    if how in MODEL_CONFIGS:
        document["config"].update(MODEL_CONFIGS[how])
        card.write_text(json.dumps(document))
        needle = next(iter(MODEL_CONFIGS[how]))
    elif how == "5000-digits":
        card.write_text(
            json.dumps(document).replace('"pfn_channels": 8', '"pfn_channels": ' + "9" * 5000)
        )
    elif how == "not-json":
        card.write_bytes(b"\xff" * 10)
    else:
        card.unlink()
        card.mkdir()
    out = tmp_path / "out"
    args = ["pseudo-label", "--model", model, "--data", world / "target", "--scale", "1",
            "--out", out, "--no-progress"]  # fmt: skip
    expect_refused(tmp_path, args, out, needle)


@pytest.mark.parametrize("given", ["file", "inline"])
@pytest.mark.parametrize("how", list(MODEL_CONFIGS)[:7])
def test_a_hostile_detector_config_is_refused_before_training(world, tmp_path, how, given):
    config = tmp_path / "detector.json"
    config.write_text(json.dumps(MODEL_CONFIGS[how]))
    if given == "inline":
        config = config.read_text()
    out = tmp_path / "out"
    args = ["pretrain", "--source", world / "source", "--out", out, "--detector-config", config]
    expect_refused(tmp_path, args, out, "--detector-config", next(iter(MODEL_CONFIGS[how])))


@pytest.mark.parametrize("value", ['{"pillar_m": ', "[1, 2]", '{"a": ' * 200 + "1" + "}" * 200,
                                   "no-such-config.json"])  # fmt: skip
def test_a_detector_config_that_is_no_json_object_is_a_usage_error(world, tmp_path, value):
    out = tmp_path / "out"
    args = ["pretrain", "--source", world / "source", "--out", out, "--detector-config", value]
    expect_refused(tmp_path, args, out, "--detector-config")


def test_an_inline_detector_config_is_the_same_as_its_file(tmp_path):
    from dali_cli.commands.pretrain import read_json_option

    document = {"direction_weight": 0.5, "x_range_m": [0.0, 40.0]}
    path = tmp_path / "detector.json"
    path.write_text(json.dumps(document))
    assert read_json_option(str(path)) == read_json_option(json.dumps(document)) == document
    assert read_json_option(None) is None


@pytest.mark.parametrize("state", [[1, 2], {"key": "x"}, "garbage"])
def test_a_hostile_resume_state_is_refused_and_says_how_to_start_over(world, tmp_path, state):
    out = tmp_path / "out"
    resume = tmp_path / "out.resume"
    resume.mkdir()
    if state == "garbage":
        (resume / "state.pt").write_bytes(b"\x80\x04garbage")
    else:
        torch.save(state, resume / "state.pt")
    args = ["pretrain", "--source", world / "source", "--out", out, "--epochs", "1",
            "--detector-config", world / "detector.json", "--no-progress"]  # fmt: skip
    expect_refused(tmp_path, args, out, "state.pt", "delete")


# ---------------------------------------------------------------------------------------------
# outputs dali does not own


def test_view_never_writes_over_an_input_or_a_user_file(world, tmp_path):
    data = tmp_path / "frames"
    shutil.copytree(world / "target", data)
    mine = tmp_path / "mine.png"
    mine.write_bytes(b"\x89PNG not dali's")
    for out in (data / "boxes.parquet", data / "frames.zarr" / "zarr.json", data / "new.png",
                mine):  # fmt: skip
        output = expect_refused(tmp_path, ["view", data, "--frame", "0", "--out", out])
        assert "--out" in output
    fresh = tmp_path / "view.png"
    assert invoke("view", data, "--frame", "0", "--out", fresh).exit_code == 0
    result = invoke("view", data, "--frame", "0", "--out", fresh)  # its own PNG: replaced
    assert result.exit_code == 0, result.output


def test_report_never_replaces_a_user_file_nor_writes_into_an_artifact(world, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(world / "model", run / "iter0" / "model")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "report.md").write_text("my notes")
    for out in (mine, run / "iter0" / "model" / "report"):
        expect_refused(tmp_path, ["report", run, "--out", out, "--no-plots"], None, "--out")


def test_eval_never_overwrites_a_user_file_beside_its_metrics_file(world, tmp_path):
    directory = tmp_path / "d"
    directory.mkdir()
    (directory / "predictions.parquet").write_text("mine")
    args = ["eval", "--model", world / "model", "--data", world / "target", "--scale", "1",
            "--out", directory / "m.json", "--no-progress"]  # fmt: skip
    expect_refused(tmp_path, args, directory / "m.json", "predictions.parquet")


def test_export_refuses_a_lock_file_that_is_a_symbolic_link(world, tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    (tmp_path / ".a2.lock").symlink_to(victim)
    out = tmp_path / "a2"
    expect_refused(tmp_path, ["export", "openpcdet", world / "target", "--out", out], out, "lock")


def test_a_full_disk_is_one_line_naming_the_output_and_the_old_output_survives(
    world, tmp_path, monkeypatch
):
    out = tmp_path / "out"
    assert invoke("export", "openpcdet", world / "target", "--out", out).exit_code == 0
    before = tree_hashes(out)
    import errno

    def full(*_args, **_kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "save", full)
    result = invoke("export", "openpcdet", world / "target", "--out", out, "--force")
    assert result.exit_code == 1 and isinstance(result.exception, SystemExit), result.output
    assert "No space left on device" in result.output and str(out) in result.output
    assert "intact" in result.output
    assert tree_hashes(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


SCALE_FILES = {
    "huge-int": b'{"scale": 1' + b"0" * 400 + b"}",
    "nan": b'{"scale": NaN}',
    "string": b'{"scale": "1.0"}',
    "list": b"[1]",
    "non-utf8": b'{"scale": \xff}',
}


@pytest.mark.parametrize("how", [*SCALE_FILES, "directory"])
def test_a_hostile_scale_file_is_refused_naming_it(world, tmp_path, how):
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    write_or_mkdir(sweep / "scale.json", SCALE_FILES.get(how))
    args = ["eval", "--model", world / "model", "--data", world / "target", "--scale-from",
            sweep, "--out", tmp_path / "m.json", "--no-progress"]  # fmt: skip
    expect_refused(tmp_path, args, tmp_path / "m.json", "scale.json")


def pretrain_on_a_full_disk(world, out):
    """`dali pretrain --out OUT` of the small world, which must stop at exit 1 with the one line
    a full disk gives (naming OUT): the result, for the caller's further checks."""
    result = invoke("pretrain", "--source", world / "source", "--out", out, "--epochs", "1",
                    "--detector-config", world / "detector.json", "--no-progress")  # fmt: skip
    assert result.exit_code == 1 and isinstance(result.exception, SystemExit), result.output
    assert f"{out}: writing failed: No space left on device" in result.output
    return result


def test_a_training_stage_refuses_a_disk_too_small_for_its_model_before_it_trains(
    world, tmp_path, monkeypatch
):
    import dali_cli.detector
    from dali_cli.store import disk_space

    def never(*_args, **_kwargs):
        raise AssertionError("trained although the model could not be saved")

    monkeypatch.setattr(dali_cli.detector, "train", never)
    monkeypatch.setattr(disk_space, "free_bytes", lambda path: 200_000)
    out = tmp_path / "model"
    result = pretrain_on_a_full_disk(world, out)
    assert "needs" in result.output and "200.0 kB (200000 bytes) free" in result.output
    assert "Traceback" not in result.output and list(tmp_path.iterdir()) == []


def test_torch_save_failing_on_a_full_disk_ends_pretrain_with_one_line(
    world, tmp_path, monkeypatch
):
    from dali_cli.store import disk_space

    def torn(value, path):
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 1544768")

    free = iter([10**12])  # room when training starts, none when the model is saved
    monkeypatch.setattr(disk_space, "free_bytes", lambda path: next(free, 1000))
    monkeypatch.setattr(torch, "save", torn)
    out = tmp_path / "model"
    result = pretrain_on_a_full_disk(world, out)
    assert "model.pt; needs" in result.output and "inline_container" not in result.output
    assert "Traceback" not in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) in ([], ["model.resume"])
