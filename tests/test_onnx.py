"""`dali export model` (ONNX, with or without --onnx): onnxruntime's boxes are the torch
detector's on real KITTI frames, at the ground of the sensor the model is for."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.detector import Detector
from dali_cli.geometry import wrap_angle
from dali_cli.sensors import get_profile
from dali_cli.store.scale_file import read_scale

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "kitti-hdl64e"
VELODYNE = Path(__file__).resolve().parent / "fixtures" / "real" / "kitti" / "training" / "velodyne"

pytest.importorskip("onnxruntime", reason="the onnx extra (make test installs it)")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("onnx") / "kitti-hdl64e"
    result = CliRunner().invoke(main, ["export", "model", str(MODEL), "--out", str(out)])
    assert result.exit_code == 0, result.output  # ONNX, the one format, without --onnx
    return out


def test_onnxruntime_boxes_equal_torchs_on_real_frames(exported):
    from dali_cli.detector.onnx_export import OnnxDetector

    frames = [np.fromfile(path, "<f4").reshape(-1, 4) for path in sorted(VELODYNE.glob("*.bin"))]
    assert len(frames) >= 1
    scale = read_scale(MODEL).scale
    detector = Detector.load(MODEL)
    # the model is for KITTI's HDL-64E: both default to its mount height (sensors.toml)
    kitti = detector.predict(frames, scale, get_profile("kitti").mount_height_m)
    torch_found = detector.predict(frames, scale)
    onnx_found = OnnxDetector(exported).predict(frames)
    total = 0
    for (boxes, scores), (onnx_boxes, onnx_scores), (kitti_boxes, _) in zip(
        torch_found, onnx_found, kitti, strict=True
    ):
        np.testing.assert_array_equal(boxes, kitti_boxes)
        assert len(boxes) == len(onnx_boxes)
        np.testing.assert_allclose(onnx_boxes[:, :6], boxes[:, :6], atol=1e-4)
        assert np.abs(wrap_angle(onnx_boxes[:, 6] - boxes[:, 6])).max(initial=0) < 1e-4
        np.testing.assert_allclose(onnx_scores, scores, atol=1e-4)
        total += len(boxes)
    assert total > 0


def test_the_export_records_its_grid_and_inputs(exported):
    import json

    spec = json.loads((exported / "onnx.json").read_text())
    assert spec["opset"] == 18 and spec["scale"] == read_scale(MODEL).scale
    assert spec["grid"]["rows"] > 0 and "heatmap" in spec["outputs"]
    assert (exported / "manifest.json").is_file() and (exported / "refiner.onnx").is_file()


def test_the_onnx_flag_asks_for_the_same_export(exported):
    """--onnx names the default format: the export made without it is up to date."""
    result = CliRunner().invoke(main, ["export", "model", str(MODEL), "--onnx", "--out",
                                       str(exported)])  # fmt: skip
    assert result.exit_code == 0 and "up to date" in result.output, result.output
