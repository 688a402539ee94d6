"""Every read of a user-given or artifact file bounded and checked (store/regular_files.py): each
reader fed each bad kind of file (a FIFO, a directory, a dangling link, a link to /dev/zero, a
4 GiB sparse file, JSON nested 200,000 deep, random bytes) refuses it within seconds, exit 1
or 2, no traceback, nothing written; and values read from artifacts are held to the options'
kinds (scale.json's scale of 1e-300 is refused as --scale 1e-300 is)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dali_cli.cli import main

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "kitti-hdl64e"
KITTI = Path(__file__).resolve().parent / "fixtures" / "real" / "kitti"
BAD_KINDS = ("fifo", "directory", "dangling", "dev-zero", "sparse-4g", "deep-json", "random")
SECONDS = 10  # a refusal takes well under one; a hang or a 4 GiB read would take far more


def make_bad(path: Path, kind: str) -> None:
    """Put a bad file of `kind` at `path` (replacing what is there)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif os.path.lexists(path):  # a file, a link, a FIFO
        path.unlink()
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "directory":
        path.mkdir()
    elif kind == "dangling":
        path.symlink_to(path.parent / "nothing-here")
    elif kind == "dev-zero":
        path.symlink_to("/dev/zero")
    elif kind == "sparse-4g":
        with open(path, "wb") as handle:
            handle.truncate(4 << 30)
    elif kind == "deep-json":
        path.write_text("[" * 200_000 + "]" * 200_000)
    else:
        path.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())


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
        if kind == "deep-json" and name == "model.pt":
            continue
        model = copy_model(tmp_path / name)
        make_bad(model / name, kind)
        out = tmp_path / name / "out"
        args = ["eval", "--model", model, "--data", frames, "--no-progress", "--out", out]
        if name == "scale.json":
            args += ["--scale-from", model]
        result, _ = run_bounded(args)
        assert_refused(result, out)


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
        result, _ = run_bounded(args)
        assert_refused(result, out)
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


def test_eval_keeps_a_users_predictions_beside_its_metrics(tmp_path, frames):
    """eval --pred DIR/predictions.parquet --out DIR/metrics.json, then eval --model --out
    DIR/metrics.json: the user's predictions are never replaced."""
    mine = tmp_path / "mine"
    mine.mkdir()
    shutil.copy(frames / "boxes.parquet", mine / "predictions.parquet")
    before = (mine / "predictions.parquet").read_bytes()
    first, _ = run_bounded(["eval", "--pred", mine / "predictions.parquet", "--gt", frames,
                            "--out", mine / "metrics.json"])  # fmt: skip
    assert first.exit_code == 0, first.output
    second, _ = run_bounded(["eval", "--model", MODEL, "--data", frames, "--no-progress",
                             "--out", mine / "metrics.json"])  # fmt: skip
    assert second.exit_code != 0 and "predictions.parquet" in second.output
    assert (mine / "predictions.parquet").read_bytes() == before
