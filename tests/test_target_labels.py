"""No DALI stage reads the target's labels, and `dali self-train` trains in the PTSN frame.

A tiny pipeline (ptsn-sweep, pseudo-label, ppcg-rc, ppcg-cf, retrain, self-train) runs on a target
whose boxes.parquet is poisoned (not Parquet at all) while every Parquet read is recorded: the
stages must succeed and never open it. The detector of ptsn-sweep / pseudo-label is a stub that
knows the cars from the test (not from the file) and predicts them with a Waymo-like size bias."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner
from test_retrain import SMALL, TOY
from toy_scenes import write_toy_dataset

from dali_cli.cli import main
from dali_cli.geometry import descale_boxes_about_ground, scale_boxes_about_ground
from dali_cli.library import procedural_car, write_library
from dali_cli.sensors import get_profile
from dali_cli.store.artifacts import FrameSet, read_boxes, write_boxes, write_frameset
from dali_cli.store.manifest import read_manifest

BIAS = np.array([1.20, 1.29, 1.14])  # Waymo / KITTI per-dimension size ratios
POISON = b"poison: DALI stages must never read the target's labels\n"


def nearest_point_key(points: np.ndarray) -> tuple:
    """A frame's identity that survives ptsn-sweep's far-point crop: its nearest point above the
    ground (the toy ground is the same in every frame, the cars are not)."""
    above = points[points[:, 2] > -1.4]  # the kitti ground is at z = -1.73
    nearest = above[np.argmin(np.hypot(above[:, 0], above[:, 1]))]
    return tuple(np.round(nearest[:3], 3))


class BiasedOracle:
    """Finds the test's cars at their scaled centres with a source-sized box (size x BIAS), on
    the ground, in the cloud scaled by `scale`; returns boxes de-scaled to the original frame."""

    def __init__(self, cars_by_key: dict, lwh: np.ndarray):
        self.cars_by_key, self.lwh = cars_by_key, lwh

    def predict(self, points_list, scale=1.0, mount_height_m=None):
        results = []
        for points in points_list:
            cars = self.cars_by_key[nearest_point_key(points)]
            scaled = scale_boxes_about_ground(cars, scale, mount_height_m)
            scaled[:, 3:6] = self.lwh * BIAS
            scaled[:, 2] = -mount_height_m + scaled[:, 5] / 2
            boxes = descale_boxes_about_ground(scaled, scale, mount_height_m)
            results.append((boxes, np.full(len(boxes), 0.9, np.float32)))
        return results


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("target-labels")
    kitti = get_profile("kitti")
    write_toy_dataset(root / "source", get_profile("waymo"), seed=1, **TOY)
    labels = write_toy_dataset(root / "target", kitti, seed=2, **TOY)
    frames = FrameSet(root / "target")
    rows = labels.rows_by_frame()
    cars_by_key = {
        nearest_point_key(points): labels.boxes[rows[frame_id]]
        for frame_id, points in frames.iter_frames()
    }
    assert len(cars_by_key) == len(frames)
    (root / "target" / "boxes.parquet").write_bytes(POISON)
    (root / "library").mkdir()
    write_library(root / "library", [procedural_car([123, 1], lod=2000)])
    (root / "config.json").write_text(json.dumps(SMALL))
    result = CliRunner().invoke(
        main,
        ["pretrain", "--source", str(root / "source"), "--out", str(root / "iter0"), "--epochs",
         "1", "--detector-config", str(root / "config.json"), "--no-progress"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    return root, BiasedOracle(cars_by_key, np.asarray(kitti.car_mean_lwh_m)), labels


def invoke(*arguments) -> None:
    result = CliRunner().invoke(main, [str(a) for a in arguments])
    assert result.exit_code == 0, result.output


def test_no_stage_reads_the_target_labels(world, monkeypatch):
    root, oracle, _ = world
    import stages.pseudo_label
    import stages.ptsn_sweep

    monkeypatch.setattr(stages.ptsn_sweep, "load_detector", lambda _: oracle)
    monkeypatch.setattr(stages.pseudo_label, "load_detector", lambda _: oracle)
    opened: list[Path] = []
    read_table = pq.read_table

    def recording_read_table(source, *args, **kwargs):
        opened.append(Path(source).resolve())
        return read_table(source, *args, **kwargs)

    monkeypatch.setattr(pq, "read_table", recording_read_table)
    target, it = root / "target", root / "iter1"
    invoke("ptsn-sweep", "--model", root / "iter0", "--data", target, "--out", it / "ptsn",
           "--no-progress")  # fmt: skip
    invoke("pseudo-label", "--model", root / "iter0", "--data", target, "--scale-from",
           it / "ptsn", "--out", it / "pseudo", "--no-progress")  # fmt: skip
    for stage in ("ppcg-rc", "ppcg-cf"):
        invoke(stage, "--data", target, "--boxes", it / "pseudo", "--library", root / "library",
               "--target-profile", "kitti", "--out", it / stage[-2:])  # fmt: skip
    invoke("retrain", "--init", root / "iter0", "--source", root / "source", "--ppcg", it / "rc",
           it / "cf", "--epochs", "1", "--no-progress", "--out", it / "model")  # fmt: skip
    invoke("self-train", "--init", it / "model", "--data", target, "--pseudo", it / "pseudo",
           "--epochs", "1", "--no-progress", "--out", it / "st")  # fmt: skip
    poisoned = (target / "boxes.parquet").resolve()
    assert opened and poisoned not in opened
    assert (target / "boxes.parquet").read_bytes() == POISON
    # the pseudo labels are what the later stages read instead
    assert (it / "pseudo" / "boxes.parquet").resolve() in opened


def test_self_train_learns_in_the_ptsn_scaled_frame(world):
    """self-train reads ŝ from the pseudo labels and trains on points and boxes scaled by it; a
    near-zero learning rate keeps the weights, a real one changes them; rerun is up to date."""
    root, _, labels = world
    import torch

    pseudo = root / "st-pseudo"
    scale = 1.15
    table = labels.with_columns(scale=np.full(len(labels), scale))
    pseudo.mkdir()
    write_boxes(pseudo, table)
    base = ["self-train", "--init", root / "iter0", "--data", root / "target", "--pseudo",
            pseudo, "--epochs", "1", "--no-progress"]  # fmt: skip
    invoke(*base, "--out", root / "st-still", "--lr", "1e-12")
    meta = json.loads((root / "st-still" / "model.json").read_text())
    assert meta["provenance"]["stage"] == "self_train"
    assert meta["provenance"]["train_scale"] == pytest.approx(scale)
    trained = read_boxes(pseudo).boxes[:, 3:6]
    # every toy car has points, so every pseudo box is a target: mean size x ŝ
    assert np.allclose(meta["metrics"]["scaled_mean_lwh_m"], trained.mean(axis=0) * scale)
    manifest = read_manifest(root / "st-still")
    assert manifest["params"]["scale"] == pytest.approx(scale) and manifest["runtime"]["threads"]

    def weights(directory):
        state = torch.load(directory / "model.pt", weights_only=True)
        return {k: v for k, v in state.items() if k.endswith("weight") and v.ndim == 4}  # convs

    before, still = weights(root / "iter0"), weights(root / "st-still")
    assert all(torch.allclose(before[k], still[k], atol=1e-6) for k in before)
    invoke(*base, "--out", root / "st-moved", "--lr", "1e-2")
    moved = weights(root / "st-moved")
    assert not all(torch.allclose(before[k], moved[k], atol=1e-6) for k in before)
    again = CliRunner().invoke(main, [str(a) for a in base] + ["--out", str(root / "st-still"),
                                                                "--lr", "1e-12"])  # fmt: skip
    assert again.exit_code == 0 and "up to date" in again.output


def test_self_train_writes_the_sensor_it_adapts_to_into_model_json(world):
    """A self-trained model is for the target's scans: model.json's config names the target's
    sensor, that profile's mount height and the front view its frames were cropped to, where the
    init (pretrained on the Waymo-like source) named the source's; the card keeps the source."""
    root, _, labels = world
    frames = FrameSet(root / "target")
    target = root / "target-cropped"
    write_frameset(target, list(frames.iter_frames()), sensor=frames.sensor,
                   attrs={"crop_front_deg": 100.0})  # fmt: skip
    pseudo = root / "cropped-pseudo"
    pseudo.mkdir()
    write_boxes(pseudo, labels.with_columns(scale=np.full(len(labels), 1.1)))
    invoke("self-train", "--init", root / "iter0", "--data", target, "--pseudo", pseudo,
           "--epochs", "1", "--lr", "1e-12", "--no-progress", "--out", root / "st-cropped")  # fmt: skip
    init = json.loads((root / "iter0" / "model.json").read_text())
    meta = json.loads((root / "st-cropped" / "model.json").read_text())
    kitti, waymo = get_profile("kitti"), get_profile("waymo")
    scans = ("sensor", "mount_height_m", "front_deg")
    assert [init["config"][k] for k in scans] == ["waymo", waymo.mount_height_m, None]
    assert [meta["config"][k] for k in scans] == [frames.sensor, kitti.mount_height_m, 100.0]
    assert meta["card"]["source_sensor"] == "waymo"
    assert meta["card"]["source_mount_height_m"] == waymo.mount_height_m


def test_self_train_learns_from_labels_of_the_same_scans_at_more_beams(world, monkeypatch):
    """--pseudo-from: labels made on the full scans train on the same frames thinned (their ids
    shared); without it such labels are refused as another target's, and a thinned set that
    lacks a labelled frame is refused naming that frame."""
    root, oracle, _ = world
    import stages.pseudo_label

    monkeypatch.setattr(stages.pseudo_label, "load_detector", lambda _: oracle)
    full, dense = root / "target", root / "dense-pseudo"
    invoke("pseudo-label", "--model", root / "iter0", "--data", full, "--scale", "1.1",
           "--out", dense, "--no-progress")  # fmt: skip
    frames = FrameSet(full)
    scans = list(frames.iter_frames())
    thinned = root / "target-thinned"
    write_frameset(thinned, [(fid, points[::4]) for fid, points in scans], sensor=frames.sensor)
    base = ["self-train", "--init", root / "iter0", "--data", thinned, "--pseudo", dense,
            "--epochs", "1", "--lr", "1e-12", "--no-progress"]  # fmt: skip
    refused = CliRunner().invoke(main, [str(a) for a in [*base, "--out", root / "st-refused"]])
    assert refused.exit_code != 0 and "made from target" in refused.output
    assert not (root / "st-refused").exists()
    invoke(*base, "--pseudo-from", full, "--out", root / "st-thinned")
    manifest = read_manifest(root / "st-thinned")
    assert Path(manifest["inputs"]["pseudo_from"][0]["path"]).resolve() == full.resolve()
    meta = json.loads((root / "st-thinned" / "model.json").read_text())
    assert 0 < meta["metrics"]["boxes"] <= len(read_boxes(dense))
    assert meta["provenance"]["train_scale"] == pytest.approx(1.1)
    partial = root / "target-thinned-partial"
    write_frameset(partial, [(fid, points[::4]) for fid, points in scans[1:]], sensor=frames.sensor)
    base[4] = partial
    missing = CliRunner().invoke(
        main, [str(a) for a in [*base, "--pseudo-from", full, "--out", root / "st-partial"]]
    )
    assert missing.exit_code != 0 and scans[0][0] in missing.output
    assert not (root / "st-partial").exists()
