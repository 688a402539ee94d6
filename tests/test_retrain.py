"""Tests of `dali retrain`: source + PPCG sets, alternating batches, init from the previous model
or from scratch, SN inherited from the initial model, CLI parsing of `--ppcg DIR1 DIR2`."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from click.testing import CliRunner
from toy_scenes import write_toy_dataset

from dali_cli.cli import main
from dali_cli.detector import (
    Augmentation,
    DetectorConfig,
    PillarCenterNet,
    TrainSettings,
    load_labeled,
    train,
)
from dali_cli.detector.train import batch_indices, interleave
from dali_cli.sensors import get_profile
from dali_cli.store.manifest import read_manifest

SMALL = dict(
    x_range_m=[0.0, 25.6],
    y_range_m=[-12.8, 12.8],
    pfn_channels=8,
    block_channels=[8, 16, 16],
    block_layers=[1, 1, 1],
    up_channels=8,
    head_channels=8,
)
TOY = dict(
    frames=3,
    cars_per_frame=3,
    x_range_m=(6.0, 22.0),
    y_range_m=(-9.0, 9.0),
    beams=24,
    points_per_beam=300,
    azimuth_range_deg=(-60.0, 60.0),
)


def write_toy_world(root, *kitti_sets: str):
    """root/source (Waymo-like, seed 1), one KITTI-like set per name (seeds 2, 3, ...) and
    root/config.json (SMALL): the tiny world the training tests train on."""
    write_toy_dataset(root / "source", get_profile("waymo"), seed=1, **TOY)
    for seed, name in enumerate(kitti_sets, start=2):
        write_toy_dataset(root / name, get_profile("kitti"), seed=seed, **TOY)
    (root / "config.json").write_text(json.dumps(SMALL))
    return root


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = write_toy_world(tmp_path_factory.mktemp("retrain"), "rc", "cf")
    runner = CliRunner()
    result = runner.invoke(
        main,
        ["pretrain", "--source", str(root / "source"), "--out", str(root / "iter0"), "--epochs", "1",
         "--size-norm", "sn", "--target-profile", "kitti", "--detector-config", str(root / "config.json"),
         "--no-progress"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    return root


def test_interleave_and_batches():
    assert interleave((1, 1)) == [0, 1]
    assert sorted(interleave((2, 1))) == [0, 0, 1] and interleave((2, 1))[0] == 0
    assert sorted(interleave((1, 2, 3))) == [0, 1, 1, 2, 2, 2]
    seen = np.concatenate([batch_indices(5, b, 2, seed=0, dataset=0) for b in range(5)])
    assert sorted(seen.tolist()) == sorted(list(range(5)) * 2)  # two passes, each a permutation


def test_batches_alternate_between_sets(world):
    config = DetectorConfig.from_dict(SMALL)
    source = load_labeled(world / "source", config)
    pseudo = load_labeled(world / "rc", config)
    settings = TrainSettings(epochs=2, batch_size=1, mix=(1, 1), log_every=1)
    net = PillarCenterNet(config)
    result = train(net, [source, pseudo], [Augmentation.none()] * 2, settings, progress=False)
    assert [row["dataset"] for row in result.log] == [0, 1] * 6  # epoch = 3 source batches
    assert source.mount_height_m == 2.0 and pseudo.mount_height_m == 1.73  # each set's own ground


def conv_weights(model_dir):
    state = torch.load(model_dir / "model.pt", weights_only=True)
    return {k: v for k, v in state.items() if k.endswith("weight") and v.ndim == 4}


def test_retrain_cli_from_previous_and_scratch(world):
    runner = CliRunner()
    base = ["retrain", "--init", str(world / "iter0"), "--source", str(world / "source"),
            "--ppcg", str(world / "rc"), str(world / "cf"), "--epochs", "1", "--no-progress"]  # fmt: skip
    out = world / "iter1"
    result = runner.invoke(main, [*base, "--out", str(out), "--lr", "1e-12"])
    assert result.exit_code == 0, result.output
    for name in ("model.pt", "model.json", "train_log.parquet", "manifest.json"):
        assert (out / name).is_file()
    manifest = read_manifest(out)
    assert [r["path"] for r in manifest["inputs"]["ppcg"]] == [str(world / "rc"), str(world / "cf")]
    assert manifest["outputs"]["counts"]["ppcg_frames"] == 6
    meta = json.loads((out / "model.json").read_text())
    assert meta["provenance"]["size_norm"] == "sn" and meta["provenance"]["init_from"] == "previous"
    # adapted to the target: model.json is for the PPCG frames' (KITTI-like) sensor, at its mount
    # height, where the initial model was for the source's; the card keeps the source
    initial = json.loads((world / "iter0" / "model.json").read_text())["config"]
    kitti = get_profile("kitti")
    assert (initial["sensor"], initial["mount_height_m"]) == ("waymo", 2.0)
    adapted = meta["config"]
    assert (adapted["sensor"], adapted["mount_height_m"]) == ("kitti", kitti.mount_height_m)
    assert adapted["front_deg"] is None  # full toy scans
    assert meta["card"]["source_sensor"] == "waymo"
    # the source keeps the initial model's SN: its boxes are resized to the KITTI mean
    assert np.allclose(
        meta["metrics"]["mean_lwh_m"][str(world / "source")], get_profile("kitti").car_mean_lwh_m
    )
    log = pq.read_table(out / "train_log.parquet").to_pydict()
    assert set(log["dataset"]) == {0, 1}
    before, after = conv_weights(world / "iter0"), conv_weights(out)
    assert all(
        torch.allclose(before[k], after[k], atol=1e-6) for k in before
    )  # lr ~ 0: same weights

    scratch = world / "iter1-scratch"
    result = runner.invoke(
        main,
        [*base, "--out", str(scratch), "--lr", "1e-12", "--init-from", "scratch", "--seed", "7"],
    )
    assert result.exit_code == 0, result.output
    fresh = conv_weights(scratch)
    assert not all(torch.allclose(before[k], fresh[k], atol=1e-6) for k in before)

    again = runner.invoke(main, [*base, "--out", str(out), "--lr", "1e-12"])
    assert again.exit_code == 0 and "up to date" in again.output


def test_retrain_cli_errors(world, tmp_path):
    runner = CliRunner()
    base = [
        "retrain",
        "--init",
        str(world / "iter0"),
        "--source",
        str(world / "source"),
        "--out",
        str(tmp_path / "m"),
    ]
    result = runner.invoke(main, [*base, "--ppcg", str(world / "rc"), "--mix", "1:x"])
    assert result.exit_code == 2 and "--mix" in result.output
    result = runner.invoke(main, [*base, "--ppcg", str(world / "rc"), "--mix", "1:1:1"])
    assert result.exit_code == 2
    empty = tmp_path / "empty"
    empty.mkdir()
    result = runner.invoke(main, [*base, "--ppcg", str(empty)])
    assert result.exit_code == 1 and "frames.zarr" in result.output
    assert not (tmp_path / "m").exists()
    result = runner.invoke(main, ["retrain", "--init", str(world / "source"), "--source", str(world / "source"),
                                  "--ppcg", str(world / "rc"), "--out", str(tmp_path / "m")])  # fmt: skip
    assert result.exit_code == 1 and "model.json" in result.output


def test_ppcg_sets_without_boxes_are_left_out_not_trained_as_background(world, tmp_path):
    """After a PTSN no-detection fallback the pseudo labels are empty and the PPCG frames still
    hold the target's cars: training on them would teach that cars are background."""
    import shutil

    from dali_cli.store.artifacts import BoxTable, write_boxes

    empty = tmp_path / "empty"
    shutil.copytree(world / "rc", empty)
    write_boxes(empty, BoxTable.empty())
    runner = CliRunner()
    base = ["retrain", "--init", str(world / "iter0"), "--source", str(world / "source"),
            "--epochs", "1", "--no-progress", "--lr", "1e-12"]  # fmt: skip
    mixed = runner.invoke(
        main, [*base, "--ppcg", str(empty), str(world / "rc"), "--out", str(tmp_path / "a")]
    )
    assert mixed.exit_code == 0, mixed.output
    manifest = read_manifest(tmp_path / "a")
    assert manifest["outputs"]["counts"]["ppcg_frames"] == 3  # rc's frames only
    assert any(str(empty) in note and "left out" in note for note in manifest["notes"])
    per_set = runner.invoke(
        main,
        [*base, "--ppcg", str(empty), str(world / "rc"), "--mix", "2:1:1", "--out",
         str(tmp_path / "b")],
    )  # fmt: skip
    assert per_set.exit_code == 0, per_set.output
    settings = json.loads((tmp_path / "b" / "model.json").read_text())["train"]["settings"]
    assert settings["mix"] == [2, 1]
    alone = runner.invoke(main, [*base, "--ppcg", str(empty), "--out", str(tmp_path / "c")])
    assert alone.exit_code == 0, alone.output
    log = pq.read_table(tmp_path / "c" / "train_log.parquet").to_pydict()
    assert set(log["dataset"]) == {0}  # the source only
    assert any("source frames only" in note for note in read_manifest(tmp_path / "c")["notes"])


def test_source_size_sn_shifts_the_source_to_the_given_target_size(world, tmp_path):
    """--size-norm sn replaces INIT's normalization: the source boxes get the given target
    mean (not INIT's kitti SN), the card records the new delta, and without a size it fails."""
    runner = CliRunner()
    base = ["retrain", "--init", str(world / "iter0"), "--source", str(world / "source"),
            "--ppcg", str(world / "rc"), "--epochs", "1", "--lr", "1e-12", "--no-progress"]  # fmt: skip
    target = (4.5, 1.9, 1.7)
    out = tmp_path / "sn"
    result = runner.invoke(
        main, [*base, "--out", str(out), "--size-norm", "sn", "--target-size", "4.5,1.9,1.7"]
    )
    assert result.exit_code == 0, result.output
    meta = json.loads((out / "model.json").read_text())
    assert np.allclose(meta["metrics"]["mean_lwh_m"][str(world / "source")], target, atol=1e-6)
    raw_mean = load_labeled(world / "source", DetectorConfig.from_dict(SMALL)).mean_lwh()
    assert meta["card"]["size_norm"] == "sn"
    assert np.allclose(meta["card"]["sn_delta_lwh_m"], np.asarray(target) - raw_mean, atol=1e-6)
    assert read_manifest(out)["params"]["source_size"] == "sn"

    missing = runner.invoke(main, [*base, "--out", str(tmp_path / "bad"), "--size-norm", "sn"])
    assert missing.exit_code != 0 and "target" in missing.output
    assert not (tmp_path / "bad").exists()


def test_source_size_sn_reads_e_est_from_a_ptsn_sweep(world, tmp_path):
    """--target-size-from PTSN_DIR: the source is sized to that sweep's E_est (the value make
    iter2 passes); a sweep without E_est is a clear error and writes nothing."""
    from dali_cli.store.scale_file import write_scale

    sweep = tmp_path / "ptsn"
    sweep.mkdir()
    write_scale(sweep, {"scale": 1.1, "E_est": [4.1, 1.75, 1.6]})
    runner = CliRunner()
    base = ["retrain", "--init", str(world / "iter0"), "--source", str(world / "source"),
            "--ppcg", str(world / "rc"), "--epochs", "1", "--lr", "1e-12", "--no-progress",
            "--size-norm", "sn"]  # fmt: skip
    out = tmp_path / "from-sweep"
    result = runner.invoke(main, [*base, "--target-size-from", str(sweep), "--out", str(out)])
    assert result.exit_code == 0, result.output
    meta = json.loads((out / "model.json").read_text())
    assert np.allclose(meta["metrics"]["mean_lwh_m"][str(world / "source")], [4.1, 1.75, 1.6])

    bare = tmp_path / "bare"
    bare.mkdir()
    write_scale(bare, {"scale": 1.1})
    failed = runner.invoke(
        main, [*base, "--target-size-from", str(bare), "--out", str(tmp_path / "x")]
    )
    assert failed.exit_code != 0 and "E_est" in failed.output
    assert not (tmp_path / "x").exists()
