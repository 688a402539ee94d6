"""`dali eval --size-correction per-dim`: the predicted cars resized per dimension by the factors
E_est / E_pred(ŝ) of a ptsn-sweep's scale.json (label-free), bottom face kept, on the table route
(saved predictions) and on the model route; recorded in metrics.json; errors write nothing."""

from __future__ import annotations

import json
import sys
import types

import numpy as np
import pytest
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.labels.size_correction import correct_class_sizes, factors_from_sweep
from dali_cli.store.artifacts import BoxTable, read_boxes, write_boxes

BIAS = np.array([1.0, 1.25, 0.8])  # a model's anisotropic bias: w x 1.25, h x 0.8
FLAGS = ["--protocol", "range", "--front-only", "--iou", "0.7"]


def biased(boxes: np.ndarray) -> np.ndarray:
    """boxes (N, 7) with l, w, h multiplied by BIAS, bottom face kept."""
    out = boxes.copy()
    out[:, 2] += (out[:, 5] * BIAS[2] - out[:, 5]) / 2
    out[:, 3:6] *= BIAS
    return out


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """(ground-truth frame set, its cars, biased predictions file, ptsn dir): the predictions are
    the true cars with BIAS (3D IoU 0.67 with their cars: none counts at 0.7 until corrected),
    the sweep's E_pred = E_est x BIAS as a biased model's sweep would find."""
    root = tmp_path_factory.mktemp("sizes")
    runner = CliRunner()
    made = runner.invoke(main, ["synth", "--sensor", "kitti", "--cars", "kitti", "--frames", "2",
                                "--seed", "1", "--out", str(root / "gt")])  # fmt: skip
    assert made.exit_code == 0, made.output
    truth = read_boxes(root / "gt")
    cars = truth.select(np.flatnonzero(np.asarray(truth["label"]).astype(str) == "Car"))
    table = BoxTable.from_arrays(
        cars.frame_id, biased(cars.boxes), score=np.linspace(0.9, 0.5, len(cars))
    )
    (root / "pred").mkdir()
    write_boxes(root / "pred", table)
    e_est = cars.boxes[:, 3:6].mean(axis=0)  # stands in for the SN statistics
    (root / "ptsn").mkdir()
    (root / "ptsn/scale.json").write_text(json.dumps(
        {"scale": 1.1, "E_est": e_est.tolist(), "E_pred_at_scale": (e_est * BIAS).tolist()}
    ))  # fmt: skip
    return root / "gt", cars, root / "pred", root / "ptsn"


def test_saved_predictions_are_corrected_evaluated_and_kept(scene, tmp_path):
    gt, cars, pred, sweep = scene
    ptsn = tmp_path / "ptsn"  # a copy: changed below
    ptsn.mkdir()
    (ptsn / "scale.json").write_text((sweep / "scale.json").read_text())
    runner = CliRunner()
    args = ["eval", "--pred", str(pred), "--gt", str(gt), *FLAGS]
    plain = runner.invoke(main, [*args, "--out", str(tmp_path / "plain.json")])
    assert plain.exit_code == 0, plain.output
    out = tmp_path / "sized"
    sized = runner.invoke(main, [*args, "--scale-from", str(ptsn), "--size-correction", "per-dim",
                                 "--out", str(out)])  # fmt: skip
    assert sized.exit_code == 0, sized.output
    before = json.loads((tmp_path / "plain.json").read_text())["Car"]
    metrics = json.loads((out / "metrics.json").read_text())
    # every car found in BEV before (footprint IoU 0.8), in 3D only after, then as well as in BEV
    # (2 frames hold fewer than 40 cars: AP_R40 tops out below 100, as KITTI's code does)
    assert before["bev"]["all"] > 10.0 and before["3d"]["all"] == 0.0
    assert metrics["Car"]["3d"]["all"] == metrics["Car"]["bev"]["all"] == before["bev"]["all"]
    record = metrics["size_correction"]
    assert np.allclose(record["factors_lwh"], 1 / BIAS, atol=1e-6)
    assert record["from"] == str(ptsn / "scale.json")
    assert np.allclose(metrics["sizes"]["pred"], metrics["sizes"]["gt"], atol=1e-3)
    kept = read_boxes(out / "predictions.parquet")  # the corrected boxes: what KITTI rows read
    assert np.allclose(kept.boxes, cars.boxes, atol=1e-6)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["params"]["size_correction"] == "per-dim"
    again = runner.invoke(main, [*args, "--scale-from", str(ptsn), "--size-correction", "per-dim",
                                 "--out", str(out)])  # fmt: skip
    assert again.exit_code == 0 and "is up to date" in again.output
    document = json.loads((ptsn / "scale.json").read_text())  # another sweep: other factors
    document["E_pred_at_scale"] = document["E_est"]
    (ptsn / "scale.json").write_text(json.dumps(document))
    rerun = runner.invoke(main, [*args, "--scale-from", str(ptsn), "--size-correction", "per-dim",
                                 "--out", str(out)])  # fmt: skip
    assert rerun.exit_code == 0 and "is up to date" not in rerun.output
    assert json.loads((out / "metrics.json").read_text())["size_correction"]["factors_lwh"] == [
        1.0,
        1.0,
        1.0,
    ]


def test_an_uncorrected_eval_keeps_its_old_parameters(scene, tmp_path):
    """Without a correction the manifest's parameters are what they were before the option
    existed, so make does not rerun every evaluation of an existing run."""
    gt, _, pred, _ = scene
    result = CliRunner().invoke(
        main, ["eval", "--pred", str(pred), "--gt", str(gt), *FLAGS, "--out", str(tmp_path / "e")]
    )
    assert result.exit_code == 0, result.output
    params = json.loads((tmp_path / "e/manifest.json").read_text())["params"]
    assert "size_correction" not in params
    assert "size_correction" not in json.loads((tmp_path / "e/metrics.json").read_text())


def test_errors_name_what_is_missing_and_write_nothing(scene, tmp_path):
    gt, _, pred, ptsn = scene
    runner = CliRunner()
    args = ["eval", "--pred", str(pred), "--gt", str(gt), *FLAGS]
    out = tmp_path / "out"
    no_sweep = runner.invoke(main, [*args, "--size-correction", "per-dim", "--out", str(out)])
    assert no_sweep.exit_code == 2 and "--scale-from" in no_sweep.output
    scale_only = runner.invoke(main, [*args, "--scale-from", str(ptsn), "--out", str(out)])
    assert scale_only.exit_code == 2 and "--size-correction per-dim" in scale_only.output
    old = tmp_path / "old_ptsn"
    old.mkdir()
    (old / "scale.json").write_text(json.dumps({"scale": 1.1, "E_est": [3.9, 1.6, 1.5]}))
    no_pred = runner.invoke(main, [*args, "--scale-from", str(old), "--size-correction", "per-dim",
                                   "--out", str(out)])  # fmt: skip
    assert no_pred.exit_code == 1
    assert str(old / "scale.json") in no_pred.output and "E_pred_at_scale" in no_pred.output
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name != "old_ptsn"]


def test_model_route_corrects_the_detector_output(scene, tmp_path, monkeypatch):
    """With --model the detector runs at ŝ of --scale-from and its cars are then corrected."""
    gt, cars, _, ptsn = scene
    seen = {}

    def predict_frameset(model_dir, data_dir, scale=1.0, score_min=0.0, **options):
        seen["scale"] = scale
        return BoxTable.from_arrays(
            cars.frame_id, biased(cars.boxes), score=np.full(len(cars), 0.8)
        )

    import importlib

    runtime = importlib.import_module("dali_cli.runtime.machine")  # stays importable
    fake = types.ModuleType("dali_cli.detector")
    fake.predict_frameset = predict_frameset
    monkeypatch.setitem(sys.modules, "dali_cli.runtime.machine", runtime)
    monkeypatch.setitem(sys.modules, "dali_cli.detector", fake)
    (tmp_path / "model").mkdir()
    out = tmp_path / "eval"
    result = CliRunner().invoke(main, [
        "eval", "--model", str(tmp_path / "model"), "--data", str(gt), "--scale-from", str(ptsn),
        "--size-correction", "per-dim", *FLAGS, "--out", str(out),
    ])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert seen["scale"] == 1.1
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["scale"] == 1.1 and metrics["Car"]["3d"]["all"] > 10.0
    assert np.allclose(read_boxes(out / "predictions.parquet").boxes, cars.boxes, atol=1e-6)
    old = tmp_path / "old_ptsn"  # a sweep without E_pred: refused before the detector runs
    old.mkdir()
    (old / "scale.json").write_text(json.dumps({"scale": 1.2, "E_est": [3.9, 1.6, 1.5]}))
    seen.clear()
    refused = CliRunner().invoke(main, [
        "eval", "--model", str(tmp_path / "model"), "--data", str(gt), "--scale-from", str(old),
        "--size-correction", "per-dim", *FLAGS, "--out", str(tmp_path / "refused"),
    ])  # fmt: skip
    assert refused.exit_code == 1 and "E_pred_at_scale" in refused.output
    assert seen == {} and not (tmp_path / "refused").exists()


def test_only_the_class_is_resized_bottom_face_kept():
    boxes = np.array([[10.0, 2.0, -1.0, 4.0, 1.8, 1.5, 0.3], [5.0, 1.0, -0.8, 0.8, 0.6, 1.7, 0.0]])
    labels = np.array(["Car", "Pedestrian"], dtype=object)
    out = correct_class_sizes(boxes, labels, "Car", np.array([1.0, 0.9, 1.1]))
    assert np.allclose(out[1], boxes[1])
    assert np.allclose(out[0, 3:6], [4.0, 1.62, 1.65])
    assert np.isclose(out[0, 2] - out[0, 5] / 2, boxes[0, 2] - boxes[0, 5] / 2)
    assert np.allclose(out[0, [0, 1, 6]], boxes[0, [0, 1, 6]])


@pytest.mark.parametrize("e_pred", [None, [3.9, 1.6], [3.9, 0.0, 1.5], [3.9, None, 1.5]])
def test_factors_need_three_positive_sizes(e_pred):
    with pytest.raises(ValueError, match="scale.json: field 'E_pred_at_scale'"):
        factors_from_sweep([3.9, 1.6, 1.5], e_pred, "scale.json")


def test_predictions_made_at_another_scale_are_flagged(scene, tmp_path):
    """Saved predictions whose metrics.json says they were made at another scale than the
    sweep's ŝ get a warning naming both (the factors hold at ŝ only); the same scale none."""
    gt, _, pred, ptsn = scene
    made = tmp_path / "eval_ptsn"
    made.mkdir()
    (made / "predictions.parquet").write_bytes((pred / "boxes.parquet").read_bytes())
    args = ["eval", "--pred", str(made / "predictions.parquet"), "--gt", str(gt), *FLAGS,
            "--scale-from", str(ptsn), "--size-correction", "per-dim"]  # fmt: skip
    for scale, flagged in ((1.0, True), (1.1, False)):
        (made / "metrics.json").write_text(json.dumps({"scale": scale}))
        result = CliRunner().invoke(main, args)
        assert result.exit_code == 0, result.output
        assert ("made at scale 1" in result.output) is flagged, result.output


def test_table_route_records_the_scale_its_predictions_were_made_at(scene, tmp_path):
    """The sized row of a report shows a scale: predictions saved by an eval carry that eval's
    scale into the new metrics.json; predictions from elsewhere (no metrics.json beside them)
    record none rather than a guess."""
    gt, _, pred, ptsn = scene
    made = tmp_path / "eval_ptsn"
    made.mkdir()
    (made / "predictions.parquet").write_bytes((pred / "boxes.parquet").read_bytes())
    (made / "metrics.json").write_text(json.dumps({"scale": 1.1}))
    for source, scale in ((made / "predictions.parquet", 1.1), (pred, None)):
        out = tmp_path / f"sized-{scale}"
        result = CliRunner().invoke(main, [
            "eval", "--pred", str(source), "--gt", str(gt), *FLAGS, "--scale-from", str(ptsn),
            "--size-correction", "per-dim", "--out", str(out)])  # fmt: skip
        assert result.exit_code == 0, result.output
        assert json.loads((out / "metrics.json").read_text()).get("scale") == scale


def sweep_with_false_boxes(directory, cars, e_est):
    """A ptsn dir whose sweep found the cars (score 0.9, sizes e_est x BIAS) and as many false
    boxes (score 0.4) of another size: its E_pred_at_scale, the mean of both, is not the cars'
    mean; detections.parquet keeps both at two evaluated scales around ŝ = 1.1."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from dali_cli.ptsn.detections import DETECTIONS_NAME, e_pred_at

    true_sizes = np.tile(e_est * BIAS, (len(cars), 1))
    false_sizes = np.tile(e_est * np.array([0.7, 1.0, 1.3]), (len(cars), 1))
    sizes = np.concatenate([true_sizes, false_sizes] * 2)
    count = 2 * len(cars)
    columns = {
        "scale": np.repeat([1.09, 1.11], count),
        "frame": np.tile(np.arange(count) % 2, 2),
        "l": sizes[:, 0], "w": sizes[:, 1], "h": sizes[:, 2],
        "score": np.tile(np.r_[np.full(len(cars), 0.9), np.full(len(cars), 0.4)], 2),
    }  # fmt: skip
    directory.mkdir()
    pq.write_table(pa.table(columns), directory / DETECTIONS_NAME)
    e_pred_all, _ = e_pred_at(columns, 1.1, 0.3)
    (directory / "scale.json").write_text(json.dumps(
        {"scale": 1.1, "E_est": e_est.tolist(), "E_pred_at_scale": e_pred_all.tolist(),
         "score_min": 0.3, "mean": "per-frame"}
    ))  # fmt: skip
    return directory


def test_factors_from_the_sweeps_confident_boxes_only(scene, tmp_path):
    """--size-factor-score-min: E_pred from the sweep's boxes above the cut. The false boxes
    bias the all-box mean (the cars stay off at 3D IoU 0.7); the confident boxes' mean is the
    cars' own, so their factors undo the model's bias exactly."""
    gt, cars, pred, _ = scene
    e_est = cars.boxes[:, 3:6].mean(axis=0)
    ptsn = sweep_with_false_boxes(tmp_path / "ptsn", cars, e_est)
    runner = CliRunner()
    args = ["eval", "--pred", str(pred), "--gt", str(gt), *FLAGS, "--scale-from", str(ptsn),
            "--size-correction", "per-dim"]  # fmt: skip
    all_boxes = runner.invoke(main, [*args, "--out", str(tmp_path / "all")])
    confident = runner.invoke(main, [*args, "--size-factor-score-min", "0.7",
                                     "--out", str(tmp_path / "confident")])  # fmt: skip
    assert all_boxes.exit_code == 0 and confident.exit_code == 0, confident.output
    biased_metrics = json.loads((tmp_path / "all/metrics.json").read_text())
    metrics = json.loads((tmp_path / "confident/metrics.json").read_text())
    assert biased_metrics["Car"]["3d"]["all"] == 0.0
    assert metrics["Car"]["3d"]["all"] == metrics["Car"]["bev"]["all"] > 10.0
    record = metrics["size_correction"]
    assert np.allclose(record["factors_lwh"], 1 / BIAS, atol=1e-6)
    assert record["factor_score_min"] == 0.7 and record["factor_boxes"] == len(cars)
    assert np.allclose(record["E_pred_at_scale"], e_est * BIAS)
    manifest = json.loads((tmp_path / "confident/manifest.json").read_text())
    assert manifest["params"]["size_factor_score_min"] == 0.7
    assert (
        "size_factor_score_min"
        not in json.loads((tmp_path / "all/manifest.json").read_text())["params"]
    )  # absent when not given: earlier sized evaluations stay up to date


def test_a_factor_cut_needs_a_correction_kept_boxes_and_a_cut_the_sweep_kept(scene, tmp_path):
    gt, cars, pred, old_sweep = scene  # the scene's sweep has no detections.parquet
    ptsn = sweep_with_false_boxes(tmp_path / "ptsn", cars, cars.boxes[:, 3:6].mean(axis=0))
    runner = CliRunner()
    args = ["eval", "--pred", str(pred), "--gt", str(gt), *FLAGS]
    out = tmp_path / "out"
    no_correction = runner.invoke(main, [*args, "--scale-from", str(ptsn),
                                         "--size-factor-score-min", "0.7", "--out", str(out)])  # fmt: skip
    assert no_correction.exit_code == 2 and "--size-correction per-dim" in no_correction.output
    sized = [*args, "--size-correction", "per-dim", "--out", str(out)]
    below = runner.invoke(
        main, [*sized, "--scale-from", str(ptsn), "--size-factor-score-min", "0.2"]
    )
    assert below.exit_code == 2 and "below the score cut 0.3" in below.output
    missing = runner.invoke(main, [*sized, "--scale-from", str(old_sweep),
                                   "--size-factor-score-min", "0.7"])  # fmt: skip
    assert missing.exit_code == 1 and str(old_sweep / "detections.parquet") in missing.output
    none_above = runner.invoke(main, [*sized, "--scale-from", str(ptsn),
                                      "--size-factor-score-min", "0.95"])  # fmt: skip
    assert none_above.exit_code == 1 and "no box with score >= 0.95" in none_above.output
    assert not out.exists()
