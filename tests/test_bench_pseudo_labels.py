"""bench/pseudo_labels.py (the label diagnosis): precision / recall, and which false
positives are clutter taken for a car and which are loose boxes near one."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

from dali_cli.store.artifacts import BoxTable, read_boxes, write_boxes

ROOT = Path(__file__).resolve().parent.parent


def load_bench():
    spec = importlib.util.spec_from_file_location("pseudo_labels", ROOT / "bench/pseudo_labels.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def car(x, y):
    return [x, y, -0.9, 3.9, 1.6, 1.5, 0.0]


def test_false_positives_are_split_into_clutter_and_loose_boxes(tmp_path):
    bench = load_bench()
    truth = BoxTable.from_arrays(
        ["a", "a", "b"], np.array([car(10, 0), car(40, 5), car(20, -3)]),
        num_points=np.array([80, 30, 50]),
    )  # fmt: skip
    pseudo = BoxTable.from_arrays(
        ["a", "a", "a", "b", "b"],
        np.array([
            car(10.1, 0.0),  # the first car: a true positive
            car(41.8, 5.0),  # 1.8 m off the second car: BEV IoU 0.37, a loose box near a car
            car(25.0, 20.0),  # nowhere near a car: clutter
            car(20.0, -3.0),  # true positive
            car(60.0, 30.0),  # clutter, scored high, dense
        ]),
        score=np.array([0.9, 0.45, 0.35, 0.8, 0.65]),
        num_points=np.array([70, 12, 40, 45, 330]),
    )  # fmt: skip
    (tmp_path / "target").mkdir()
    (tmp_path / "pseudo").mkdir()
    write_boxes(tmp_path / "target", truth)
    write_boxes(tmp_path / "pseudo", pseudo)
    (tmp_path / "pseudo/summary.json").write_text(json.dumps({"mean_lwh": [3.9, 1.6, 1.5]}))
    result = bench.evaluate(tmp_path / "pseudo", read_boxes(tmp_path / "target"), 0.5, 1)
    assert result["bands"]["all"]["true_positives"] == 2
    assert result["bands"]["all"]["false_positives"] == 3
    kinds = result["false_positives"]
    assert kinds["true_positives"]["boxes"] == 2
    assert kinds["near_a_car"] == {
        "boxes": 1, "median_score": 0.45, "median_points": 12.0, "dense": 0
    }  # fmt: skip
    assert kinds["hallucinated"]["boxes"] == 2 and kinds["hallucinated"]["dense"] == 1
    assert kinds["hallucinated"]["median_score"] == 0.5  # of 0.35 and 0.65
    cuts = result["score_cuts"]
    assert cuts["0.3"] == {"true_positives": 2, "false_positives": 3, "hallucinated": 2}
    assert cuts["0.4"] == {"true_positives": 2, "false_positives": 2, "hallucinated": 1}
    assert cuts["0.6"] == {"true_positives": 2, "false_positives": 1, "hallucinated": 1}
