"""`dali compare` and dali_cli.evaluation.bootstrap: rows evaluated on all frames and on paired draws of the
frames with replacement, with the difference to the first row; errors write nothing."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.evaluation.bootstrap import FrameIndex, paired_bootstrap, resampled
from dali_cli.evaluation.evaluate import evaluate
from dali_cli.store.artifacts import BoxTable, read_boxes, write_boxes

FLAGS = ["--protocol", "range", "--front-only", "--iou", "0.7"]


def table(frames, xs, scores=None):
    boxes = np.zeros((len(xs), 7))
    boxes[:, 0], boxes[:, 3:6] = xs, (4.0, 1.8, 1.5)
    return BoxTable.from_arrays(frames, boxes, score=scores)


def test_a_draw_takes_each_drawn_frame_whole_under_its_draw_position():
    universe = np.array(["a", "b", "c"])
    boxes = table(["c", "a", "c", "b"], [1.0, 2.0, 3.0, 4.0])
    rows, ids = FrameIndex(boxes, universe).rows(np.array([2, 0, 2]))
    assert rows.tolist() == [0, 2, 1, 0, 2] and ids.tolist() == ["0", "0", "1", "2", "2"]
    drawn = resampled(boxes, FrameIndex(boxes, universe), np.array([1, 1]))
    assert drawn.frame_id.tolist() == ["0", "1"] and drawn["x"].tolist() == [4.0, 4.0]
    empty = FrameIndex(table([], []), universe).rows(np.array([0, 1]))
    assert len(empty[0]) == 0 and len(empty[1]) == 0


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """(truth dir, perfect predictions, predictions that miss the cars of every second frame)."""
    root = tmp_path_factory.mktemp("compare")
    made = CliRunner().invoke(main, ["synth", "--sensor", "kitti", "--cars", "kitti",
                                     "--frames", "6", "--seed", "2", "--out", str(root / "gt")])  # fmt: skip
    assert made.exit_code == 0, made.output
    truth = read_boxes(root / "gt")
    cars = truth.select(np.flatnonzero(np.asarray(truth["label"]).astype(str) == "Car"))
    scores = np.linspace(0.95, 0.4, len(cars))
    perfect = BoxTable.from_arrays(cars.frame_id, cars.boxes, score=scores)
    frames = sorted(set(cars.frame_id.astype(str)))
    keep = ~np.isin(cars.frame_id.astype(str), frames[::2])
    missing = perfect.select(np.flatnonzero(keep))
    paths = {}
    for name, rows in (("perfect", perfect), ("missing", missing)):
        (root / name).mkdir()
        write_boxes(root / name, rows)
        paths[name] = root / name
    return root / "gt", paths


def metric_3d(pred, gt):
    block = evaluate(pred, gt, iou=0.7, protocol="range", front_only=True)["Car"]
    return {"3d all": block["3d"]["all"]}


def test_paired_draws_see_identical_rows_as_identical_and_a_worse_row_as_worse(scene):
    gt_path, paths = scene
    gt = read_boxes(gt_path)
    perfect, missing = read_boxes(paths["perfect"]), read_boxes(paths["missing"])
    result = paired_bootstrap({"a": perfect, "b": perfect, "c": missing}, gt, metric_3d,
                              samples=30, seed=4)  # fmt: skip
    summary = result.summary()["rows"]
    assert summary["b"]["3d all"]["delta_std"] == 0.0  # the same draw for both rows
    assert summary["b"]["3d all"]["share_not_above_reference"] == 1.0
    assert (
        summary["c"]["3d all"]["delta"] < -20 and summary["c"]["3d all"]["delta_interval_95"][1] < 0
    )
    assert summary["c"]["3d all"]["share_not_above_reference"] == 1.0
    assert result.full[0, 0] == pytest.approx(metric_3d(perfect, gt)["3d all"])
    assert 0 < summary["c"]["3d all"]["std"]  # another draw, another AP
    again = paired_bootstrap({"a": perfect, "c": missing}, gt, metric_3d, samples=30, seed=4)
    assert np.array_equal(again.samples[:, 1], result.samples[:, 2])  # seeded draws
    other = paired_bootstrap({"a": perfect, "c": missing}, gt, metric_3d, samples=30, seed=5)
    assert not np.array_equal(other.samples[:, 1], result.samples[:, 2])


def test_cli_compares_rows_as_dali_eval_scores_them(scene, tmp_path):
    gt_path, paths = scene
    runner = CliRunner()
    out = tmp_path / "cmp.json"
    args = ["compare", "--gt", str(gt_path), "--pred", f"full={paths['perfect']}",
            "--pred", f"half={paths['missing']}", *FLAGS, "--samples", "20", "--no-progress"]  # fmt: skip
    result = runner.invoke(main, [*args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "reference: full" in result.output and "P(Δ<=0)" in result.output
    document = json.loads(out.read_text())
    evaluated = runner.invoke(main, ["eval", "--pred", str(paths["missing"]), "--gt", str(gt_path),
                                     *FLAGS, "--out", str(tmp_path / "m.json")])  # fmt: skip
    assert evaluated.exit_code == 0, evaluated.output
    metrics = json.loads((tmp_path / "m.json").read_text())["Car"]
    half = document["bootstrap"]["rows"]["half"]
    assert half["3d all"]["ap"] == pytest.approx(metrics["3d"]["all"], abs=1e-4)
    assert half["bev 50-80"]["ap"] == pytest.approx(metrics["bev"]["50-80"], abs=1e-4)
    assert document["bootstrap"]["samples"] == 20 and document["settings"]["iou"] == 0.7
    again = runner.invoke(main, [*args, "--out", str(out)])  # its own file: replaced
    assert again.exit_code == 0, again.output


def test_cli_errors_name_the_problem_and_write_nothing(scene, tmp_path):
    gt_path, paths = scene
    runner = CliRunner()
    base = ["compare", "--gt", str(gt_path), *FLAGS, "--no-progress"]
    one = runner.invoke(main, [*base, "--pred", f"a={paths['perfect']}"])
    assert one.exit_code == 2 and "at least two" in one.output
    twice = runner.invoke(main, [*base, "--pred", f"a={paths['perfect']}",
                                 "--pred", f"a={paths['missing']}"])  # fmt: skip
    assert twice.exit_code == 2 and "'a' given twice" in twice.output
    absent = runner.invoke(main, [*base, "--pred", f"a={paths['perfect']}",
                                  "--pred", f"b={tmp_path / 'nope'}"])  # fmt: skip
    assert absent.exit_code == 2 and "nope" in absent.output
    assert "cannot contain" not in absent.output  # no path after another "=": no hint
    equals = runner.invoke(main, [*base, "--pred", f"a={paths['perfect']}",
                                  "--pred", f"cars >= 0.6={paths['missing']}"])  # fmt: skip
    assert equals.exit_code == 2, equals.output
    assert "a row name cannot contain '='" in equals.output and "'cars >= 0.6'" in equals.output
    foreign = tmp_path / "notes.json"
    foreign.write_text('{"mine": 1}')
    rows = ["--pred", f"a={paths['perfect']}", "--pred", f"b={paths['missing']}"]
    refused = runner.invoke(main, [*base, *rows, "--out", str(foreign)])
    assert refused.exit_code != 0 and "not a dali metrics file" in refused.output
    assert json.loads(foreign.read_text()) == {"mine": 1}
    into_input = runner.invoke(main, [*base, *rows, "--out", str(paths["perfect"] / "x.json")])
    assert into_input.exit_code != 0
    assert not (paths["perfect"] / "x.json").exists()
    not_json = runner.invoke(main, [*base, *rows, "--out", str(tmp_path / "cmp.txt")])
    assert not_json.exit_code == 2 and not (tmp_path / "cmp.txt").exists()
