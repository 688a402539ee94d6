"""The model card (one typed reader of what training recorded about a model) and safe loading
of model files."""

from __future__ import annotations

import json
import pickle
import shutil

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.detector import Detector
from dali_cli.store.artifacts import ArtifactError, read_boxes
from dali_cli.store.model_card import ModelCard, read_card
from stages.ptsn_sweep import read_model_card, resolve_e_est
from tests.test_retrain import write_toy_world

ROS_RANGE = (0.7, 0.9)


@pytest.fixture(scope="module")
def ros_world(tmp_path_factory):
    """A real (tiny) checkpoint pretrained with ROS, and one retrained from it."""
    root = write_toy_world(tmp_path_factory.mktemp("card"), "target")
    runner = CliRunner()
    common = ["--epochs", "1", "--detector-config", str(root / "config.json"), "--no-progress"]
    result = runner.invoke(
        main,
        ["pretrain", "--source", str(root / "source"), "--out", str(root / "iter0"),
         "--size-norm", "ros", "--ros-range", "0.7,0.9", *common],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    result = runner.invoke(
        main,
        ["retrain", "--init", str(root / "iter0"), "--source", str(root / "source"), "--ppcg",
         str(root / "target"), "--out", str(root / "iter1"), "--epochs", "1", "--no-progress"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    return root


def test_ros_expected_size_uses_the_real_checkpoints_card(ros_world):
    """`--target-size ros` read top-level keys that pretrain never wrote, so a real checkpoint
    silently fell back to the default factor and the profile's size."""
    labels = read_boxes(ros_world / "source")
    source_mean = labels.boxes[:, 3:6].mean(axis=0)  # every toy car has points
    for model in ("iter0", "iter1"):  # the retrained model carries the card forward
        card = read_model_card(ros_world / model)
        assert card.ros_range == ROS_RANGE and card.source_sensor == "waymo"
        np.testing.assert_allclose(card.source_mean_lwh_m, source_mean, rtol=1e-6)
        lwh, record = resolve_e_est(
            "ros",
            target_profile="kitti",
            card=card,
            source_profile=None,
            ros_factor=None,
            sensors_path=None,
        )
        np.testing.assert_allclose(lwh, source_mean * np.mean(ROS_RANGE), rtol=1e-6)
        assert record["ros_factor"] == pytest.approx(0.8)
    assert read_card(ros_world / "iter1").stage == "retrain"


def test_the_sweep_records_the_cards_ros_size(ros_world):
    out = ros_world / "ptsn"
    result = CliRunner().invoke(
        main,
        ["ptsn-sweep", "--model", str(ros_world / "iter0"), "--data", str(ros_world / "target"),
         "--target-size", "ros", "--search", "grid", "--scales", "0.9:1.1:0.1", "--no-progress",
         "--out", str(out)],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    document = json.loads((out / "scale.json").read_text())
    expected = np.asarray(read_card(ros_world / "iter0").source_mean_lwh_m) * 0.8
    np.testing.assert_allclose(document["E_est"], expected, rtol=1e-5)


def test_cards_of_checkpoints_written_before_the_card_existed():
    legacy = {
        "detector": "pillar-centerpoint-iou",
        "config": {"sensor": "waymo", "mount_height_m": 2.1, "name": "pillar-centerpoint-iou"},
        "provenance": {"stage": "pretrain", "source_sensor": "waymo", "size_norm": "ros",
                       "ros_range": [0.75, 1.0], "sn_delta_lwh": None},
        "metrics": {"source_mean_lwh_m": [4.8, 2.1, 1.8]},
    }  # fmt: skip
    card = ModelCard.from_meta(legacy)
    assert card.ros_range == (0.75, 1.0) and card.ros_factor == pytest.approx(0.875)
    assert card.source_mean_lwh_m == (4.8, 2.1, 1.8) and card.source_mount_height_m == 2.1
    assert ModelCard.from_meta({**legacy, "card": card.to_dict()}) == card  # round trip


class Exploit:
    """A pickle that would create a marker file when unpickled with the full unpickler."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_a_malicious_model_or_training_state_is_refused_and_runs_nothing(ros_world, tmp_path):
    marker = tmp_path / "pwned"
    model = tmp_path / "model"
    shutil.copytree(ros_world / "iter0", model)
    torch.save({"weights": Exploit(marker)}, model / "model.pt")
    with pytest.raises(ArtifactError, match="model.pt: not dali model weights"):
        Detector.load(model)
    result = CliRunner().invoke(
        main,
        ["eval", "--model", str(model), "--data", str(ros_world / "target"), "--out",
         str(tmp_path / "eval" / "metrics.json")],
    )  # fmt: skip
    assert (
        result.exit_code == 1 and "model.pt" in result.output and "Traceback" not in result.output
    )
    assert not (tmp_path / "eval").exists()
    # a resume state beside an output (it must load with weights_only=True)
    out = tmp_path / "iter0b"
    resume = tmp_path / "iter0b.resume" / "state.pt"
    resume.parent.mkdir()
    torch.save({"key": "x", "net": Exploit(marker)}, resume)
    result = CliRunner().invoke(
        main,
        ["pretrain", "--source", str(ros_world / "source"), "--out", str(out), "--epochs", "1",
         "--detector-config", str(ros_world / "config.json"), "--no-progress"],
    )  # fmt: skip
    assert result.exit_code == 1 and "state.pt" in result.output
    assert not marker.exists() and not out.exists()


@pytest.mark.parametrize("damage", ["not-a-pickle", "plain-pickle", "bad-json", "wrong-shapes"])
def test_a_foreign_model_file_is_a_clear_error(ros_world, tmp_path, damage):
    model = tmp_path / "model"
    shutil.copytree(ros_world / "iter0", model)
    if damage == "not-a-pickle":
        (model / "model.pt").write_bytes(b"GIF89a not weights at all")
    elif damage == "plain-pickle":
        (model / "model.pt").write_bytes(pickle.dumps({"a": 1}))
    elif damage == "bad-json":
        (model / "model.json").write_text("{not json")
    else:
        meta = json.loads((model / "model.json").read_text())
        meta["config"]["head_channels"] = 16
        (model / "model.json").write_text(json.dumps(meta))
    for command in (
        ["eval", "--model", str(model), "--data", str(ros_world / "target")],
        ["pseudo-label", "--model", str(model), "--data", str(ros_world / "target"),
         "--scale", "1", "--out", str(tmp_path / "pseudo")],
        ["retrain", "--init", str(model), "--source", str(ros_world / "source"), "--ppcg",
         str(ros_world / "target"), "--out", str(tmp_path / "re"), "--epochs", "1", "--no-progress"],
    ):  # fmt: skip
        result = CliRunner().invoke(main, command)
        assert result.exit_code == 1, (command[0], result.output)
        assert "Traceback" not in result.output and str(model) in result.output
    assert not (tmp_path / "pseudo").exists() and not (tmp_path / "re").exists()


def test_the_front_view_a_frame_set_was_cropped_to():
    """What training records as the model's front view (model.json config front_deg): an
    odometry crop's angle, --crop-fov's camera view, a merge's widest when every part was
    cropped, none as soon as one part holds full scans."""
    from dali_cli.detector.scans_for import CAMERA_VIEW_DEG, cropped_front_deg

    odometry = {"source_format": "kitti-odometry", "crop_fov": False, "crop_front_deg": 90.0}
    raw = {"source_format": "kitti-raw", "crop_fov": True}
    full = {"source_format": "kitti-raw", "crop_fov": False}
    assert cropped_front_deg(odometry) == 90.0 and cropped_front_deg(raw) == CAMERA_VIEW_DEG
    assert cropped_front_deg(full) is None and cropped_front_deg({}) is None
    merged = {"source_format": "merge", "drives": {"a": raw, "b": odometry}}
    assert cropped_front_deg(merged) == max(90.0, CAMERA_VIEW_DEG)
    assert cropped_front_deg({"drives": {"a": raw, "b": full}}) is None
    assert cropped_front_deg({**odometry, "crop_front_deg": float("nan")}) is None
