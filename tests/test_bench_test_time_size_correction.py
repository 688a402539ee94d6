"""bench/test_time_size_correction.py (issue 18's stronger control): a model's predictions resized
per dimension by its own sweep's label-free E_est / E_pred, evaluated again, and with --out kept
as an eval directory of their own."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from dali_cli.artifacts import BoxTable, read_boxes, write_boxes

REPO = Path(__file__).resolve().parents[1]
DALI = str(Path(sys.executable).with_name("dali"))


def test_a_known_size_bias_is_removed_and_the_row_kept(tmp_path):
    gt_dir = tmp_path / "target_val"
    subprocess.run(
        [DALI, "synth", "--sensor", "kitti", "--cars", "kitti", "--frames", "2", "--seed", "1",
         "--out", str(gt_dir)], check=True, capture_output=True,
    )  # fmt: skip
    truth = read_boxes(gt_dir)
    truth = truth.select(np.flatnonzero(np.asarray(truth["label"]).astype(str) == "Car"))
    # predictions = the true cars with a model's anisotropic bias (w x 1.25, h x 0.8, bottom
    # kept): 3D IoU 0.67 with their cars, so none counts at 0.7 until the bias is removed
    factors = np.array([1.0, 1.25, 0.8])
    biased = truth.boxes.copy()
    biased[:, 2] += (biased[:, 5] * factors[2] - biased[:, 5]) / 2
    biased[:, 3:6] *= factors
    (tmp_path / "eval").mkdir()
    table = BoxTable.from_arrays(truth.frame_id, biased, score=np.linspace(0.9, 0.5, len(truth)))
    write_boxes(tmp_path / "eval", table)
    (tmp_path / "eval/boxes.parquet").rename(tmp_path / "eval/predictions.parquet")
    e_est = truth.boxes[:, 3:6].mean(axis=0)  # stands in for the SN statistics
    (tmp_path / "ptsn").mkdir()
    (tmp_path / "ptsn/scale.json").write_text(json.dumps(
        {"scale": 1.1, "E_est": e_est.tolist(), "E_pred_at_scale": (e_est * factors).tolist()}
    ))  # fmt: skip
    out = tmp_path / "row"
    result = subprocess.run(
        [sys.executable, str(REPO / "bench/test_time_size_correction.py"), str(tmp_path / "eval"),
         str(tmp_path / "ptsn"), "--gt", str(gt_dir), "--out", str(out)],
        check=True, capture_output=True, text=True,
    )  # fmt: skip
    record = json.loads(result.stdout.strip().splitlines()[-1])
    assert np.allclose(record["factors_lwh"], 1 / factors, atol=1e-4)
    # every car found in BEV before (footprint IoU 0.8); in 3D only after, then as well as in BEV
    # (2 frames hold fewer than 40 cars, so AP_R40 tops out below 100, as KITTI's code does)
    assert record["before"]["bev"] > 10.0
    assert record["before"]["3d"] == 0.0
    assert record["after"]["3d"] == record["after"]["bev"] == record["before"]["bev"]
    kept = read_boxes(out / "predictions.parquet")
    assert np.allclose(kept.boxes, truth.boxes, atol=1e-6)
    assert (
        json.loads((out / "metrics.json").read_text())["Car"]["3d"]["all"] == record["after"]["3d"]
    )
    assert "moderate" in json.loads((out / "metrics_kitti.json").read_text())["Car"]["3d"]
