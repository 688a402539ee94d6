"""The fuzz suite's reads and values (tests/test_fuzz.py has its options and documents), the
classes of bench/hostile_inputs.py. Every read of a user-given or artifact file bounded and
checked (store/regular_files.py): each reader fed each bad kind of file (a FIFO, a directory, a dangling link, a link to /dev/zero, a
4 GiB sparse file, JSON nested 200,000 deep, random bytes) refuses it within seconds, exit 1
or 2, no traceback, nothing written; and values read from artifacts are held to the options'
kinds (scale.json's scale of 1e-300 is refused as --scale 1e-300 is)."""

from __future__ import annotations

import json
import shutil
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hostile_files import box_table_with, make_bad

from dali_cli.cli import main

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "kitti-hdl64e"
KITTI = Path(__file__).resolve().parent / "fixtures" / "real" / "kitti"
BAD_KINDS = (
    "fifo",
    "directory",
    "dangling",
    "dev-zero",
    "sparse-4g",
    "deep-json",
    "random",
)  # of hostile_files
SECONDS = 10  # a refusal takes well under one; a hang or a 4 GiB read would take far more
REFUSAL_S = 3.0  # a sparse 4 GiB file refused by stat: milliseconds; hashing it first: 4 s or more


def run_bounded(args: list) -> tuple[object, float]:
    """The CliRunner result of `dali ARGS` and its seconds; the test fails after SECONDS (a
    hang) instead of blocking the suite."""

    def expire(*_):
        raise TimeoutError(f"dali {' '.join(map(str, args))} ran over {SECONDS} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(SECONDS)
    started = time.perf_counter()
    try:
        result = CliRunner().invoke(main, [str(a) for a in args])
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    return result, time.perf_counter() - started


def assert_refused(result, out: Path | None = None) -> None:
    assert result.exit_code in (1, 2), (result.exit_code, result.output, result.exception)
    assert not isinstance(result.exception, TimeoutError), result.exception
    assert "Traceback" not in result.output
    if out is not None:
        assert not out.exists()


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("reads") / "frames"
    result = CliRunner().invoke(
        main, ["import", "kitti", str(KITTI), "--no-progress", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    return out


def copy_model(tmp_path: Path) -> Path:
    model = tmp_path / "model"
    shutil.copytree(MODEL, model)
    return model


@pytest.mark.parametrize("kind", BAD_KINDS)
def test_model_and_scale_files(tmp_path, frames, kind):
    for name in ("model.json", "scale.json", "model.pt"):
        for command in ("eval", "pseudo-label", "ptsn-sweep"):
            if (kind == "deep-json" and name == "model.pt") or (
                command == "ptsn-sweep" and name == "scale.json"  # a sweep does not read it
            ):
                continue
            model = copy_model(tmp_path / command / name)
            make_bad(model / name, kind)
            out = tmp_path / command / name / "out"
            args = [command, "--model", model, "--data", frames, "--no-progress", "--out", out]
            if command == "pseudo-label" or name == "scale.json":
                args += ["--scale-from", model]
            result, seconds = run_bounded(args)
            assert_refused(result, out)
            if kind == "sparse-4g":  # refused by its size, not after hashing 4 GiB
                assert seconds < REFUSAL_S, (command, name, seconds)


@pytest.mark.parametrize("kind", BAD_KINDS)
def test_configs_and_sensor_files(tmp_path, kind):
    config = tmp_path / "cfg.json"
    make_bad(config, kind)
    out = tmp_path / "out"
    result, _ = run_bounded(["pretrain", "--source", tmp_path, "--detector-config", config,
                             "--out", out])  # fmt: skip
    assert_refused(result, out)
    sensors = tmp_path / "sensors.toml"
    make_bad(sensors, kind)
    result, _ = run_bounded(["synth", "--sensors", sensors, "--frames", "1", "--out", out])
    assert_refused(result, out)


@pytest.mark.parametrize("kind", BAD_KINDS)
def test_frame_set_metadata_and_box_tables(tmp_path, frames, kind):
    for relative in ("frames.zarr/points/zarr.json", "boxes.parquet"):
        copy = tmp_path / relative.replace("/", "_") / "frames"
        shutil.copytree(frames, copy)
        make_bad(copy / relative, kind)
        png = copy.parent / "v.png"
        result, _ = run_bounded(["view", copy, "--frame", "0", "--out", png])
        assert_refused(result, png)


@pytest.mark.parametrize("kind", BAD_KINDS)
def test_kitti_label_calib_and_id_files(tmp_path, kind):
    root = tmp_path / "kitti"
    shutil.copytree(KITTI, root)
    training = root / "training"
    frame = sorted((training / "label_2").glob("*.txt"))[0].stem
    for target in (training / "label_2" / f"{frame}.txt", training / "calib" / f"{frame}.txt",
                   tmp_path / "ids.txt"):  # fmt: skip
        out = tmp_path / f"out-{target.parent.name}"
        make_bad(target, kind)
        args = ["import", "kitti", root, "--no-progress", "--out", out]
        if target.name == "ids.txt":
            args += ["--ids", target]
        result, seconds = run_bounded(args)
        assert_refused(result, out)
        if kind == "sparse-4g":
            assert seconds < REFUSAL_S, (target, seconds)
        original = KITTI / "training" / target.parent.name / target.name
        make_bad(target, "random")  # clears the bad kind, then the original goes back
        target.unlink()
        if original.is_file():
            shutil.copy(original, target)


@pytest.mark.parametrize(
    "field, value",
    [("scale", 1e-300), ("scale", 1e308), ("scale", "1.2"), ("E_est", [0, 0, 0]),
     ("E_est", [float("nan"), 1, 1]), ("E_est", [4, 1.6]), ("E_est", "big")],
)  # fmt: skip
def test_scale_json_values_are_held_to_the_options_kinds(tmp_path, frames, field, value):
    model = copy_model(tmp_path)
    document = json.loads((model / "scale.json").read_text())
    document[field] = value
    (model / "scale.json").write_text(json.dumps(document))
    out = tmp_path / "out"
    result, seconds = run_bounded(["eval", "--model", model, "--data", frames, "--scale-from",
                                   model, "--no-progress", "--out", out])  # fmt: skip
    assert_refused(result, out)
    assert f"'{field}'" in result.output


def test_a_model_json_naming_another_detector_is_refused(tmp_path, frames):
    model = copy_model(tmp_path)
    document = json.loads((model / "model.json").read_text())
    document["detector"] = "nosuch"
    (model / "model.json").write_text(json.dumps(document))
    result, _ = run_bounded(["eval", "--model", model, "--data", frames, "--no-progress",
                             "--out", tmp_path / "out"])  # fmt: skip
    assert_refused(result, tmp_path / "out")
    assert "nosuch" in result.output


@pytest.mark.parametrize(
    "content, found",
    [(lambda p: p * np.array([1, 1, 1, 255], np.float32), "intensity from"),
     (lambda p: np.zeros_like(p), "no valid point"),
     (lambda p: p * np.array([1e6, 1, 1, 1], np.float32), "beyond any LiDAR"),
     (lambda p: np.frombuffer((ROOT / "README.md").read_bytes()[:1600], "<f4").reshape(-1, 4), "")],
)  # fmt: skip
def test_imports_keep_the_frame_set_contract(tmp_path, content, found):
    root = tmp_path / "kitti"
    shutil.copytree(KITTI, root)
    scan = sorted((root / "training" / "velodyne").glob("*.bin"))[0]
    points = np.fromfile(scan, "<f4").reshape(-1, 4)
    content(points).astype("<f4").tofile(scan)
    out = tmp_path / "out"
    result, _ = run_bounded(["import", "kitti", root, "--no-progress", "--out", out])
    assert_refused(result, out)
    assert scan.name in result.output and found in result.output


def test_intensity_max_rescales_and_is_recorded(tmp_path):
    root = tmp_path / "kitti"
    shutil.copytree(KITTI, root)
    for scan in (root / "training" / "velodyne").glob("*.bin"):
        points = np.fromfile(scan, "<f4").reshape(-1, 4)
        (points * np.array([1, 1, 1, 255], np.float32)).astype("<f4").tofile(scan)
    out = tmp_path / "out"
    result, _ = run_bounded(["import", "kitti", root, "--intensity-max", "255", "--no-progress",
                             "--out", out])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert json.loads((out / "manifest.json").read_text())["params"]["intensity_max"] == 255


@pytest.mark.parametrize("form", ["DIR/metrics.json", "DIR"])
def test_eval_keeps_a_users_predictions_beside_its_metrics(tmp_path, frames, form):
    """eval --pred DIR/predictions.parquet --out DIR/metrics.json, then eval --model --out
    DIR/metrics.json or --out DIR: the user's predictions are never replaced."""
    mine = tmp_path / "mine"
    mine.mkdir()
    shutil.copy(frames / "boxes.parquet", mine / "predictions.parquet")
    before = (mine / "predictions.parquet").read_bytes()
    first, _ = run_bounded(["eval", "--pred", mine / "predictions.parquet", "--gt", frames,
                            "--out", mine / "metrics.json"])  # fmt: skip
    assert first.exit_code == 0, first.output
    out = mine / "metrics.json" if form == "DIR/metrics.json" else mine
    second, _ = run_bounded(["eval", "--model", MODEL, "--data", frames, "--no-progress",
                             "--out", out])  # fmt: skip
    assert second.exit_code != 0
    assert ("predictions.parquet" if out != mine else "without a dali manifest") in second.output
    assert (mine / "predictions.parquet").read_bytes() == before


@pytest.mark.parametrize(
    "columns, found",
    [({"score": -1.0}, "-1"), ({"l": 0.0, "score": 0.9}, "size"),
     ({"frame_id": "nosuch", "score": 0.9}, "frame")],
)  # fmt: skip
def test_eval_refuses_predictions_it_cannot_score(tmp_path, frames, columns, found):
    pred = box_table_with(frames, tmp_path / "pred.parquet", **columns)
    out = tmp_path / "m.json"
    result, _ = run_bounded(["eval", "--pred", pred, "--gt", frames, "--out", out])
    assert_refused(result, out)
    assert found in result.output


@pytest.mark.parametrize(
    "columns", [{"l": 1e308}, {"l": float("nan")}, {"h": -1.0}, {"frame_id": "nosuch"}]
)
def test_view_and_export_refuse_impossible_boxes(tmp_path, frames, columns):
    copy = tmp_path / "frames"
    shutil.copytree(frames, copy)
    box_table_with(frames, tmp_path / "b.parquet", **columns).replace(copy / "boxes.parquet")
    png = tmp_path / "v.png"
    result, _ = run_bounded(["view", copy, "--frame", "0", "--out", png])
    assert_refused(result, png)
    result, _ = run_bounded(["export", "openpcdet", copy, "--out", tmp_path / "pcdet"])
    assert_refused(result, tmp_path / "pcdet")


def test_an_empty_id_list_is_refused(tmp_path):
    (tmp_path / "ids.txt").write_text("")
    out = tmp_path / "out"
    result, _ = run_bounded(["import", "kitti", KITTI, "--ids", tmp_path / "ids.txt",
                             "--no-progress", "--out", out])  # fmt: skip
    assert_refused(result, out)
    assert "ids.txt" in result.output


def test_a_png_output_that_is_a_link_is_refused_even_dangling(tmp_path, frames):
    """--out f.png a symbolic link to nothing: writing would follow it (or replace the user's
    link); refused like a link to a file."""
    png = tmp_path / "f.png"
    png.symlink_to(tmp_path / "elsewhere.png")
    result, _ = run_bounded(["view", frames, "--frame", "0", "--out", png])
    assert_refused(result)
    assert png.is_symlink() and not (tmp_path / "elsewhere.png").exists()
