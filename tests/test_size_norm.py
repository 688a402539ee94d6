"""`dali size-norm`: the source seen with a model's size convention (the forgetting check's data)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.detector.size_norm import shift_frame
from dali_cli.store.artifacts import BoxTable, FrameSet, read_boxes, write_boxes, write_frameset

DELTA = np.array([-0.6, -0.4, -0.2])


def _car_points(box: np.ndarray, count: int, rng) -> np.ndarray:
    """`count` points inside `box` (7,), as (n, 4) float32 in the sensor frame."""
    local = rng.uniform(-0.45, 0.45, (count, 3)) * box[3:6]
    cos, sin = np.cos(box[6]), np.sin(box[6])
    xyz = np.stack(
        [box[0] + cos * local[:, 0] - sin * local[:, 1],
         box[1] + sin * local[:, 0] + cos * local[:, 1],
         box[2] + local[:, 2]], axis=1,
    )  # fmt: skip
    return np.concatenate([xyz, rng.uniform(0, 1, (count, 1))], axis=1).astype(np.float32)


def test_shift_frame_resizes_boxes_about_their_bottom_and_moves_only_their_points():
    rng = np.random.default_rng(0)
    boxes = np.array(
        [[12.0, 3.0, -1.1, 4.6, 2.1, 1.8, 0.4], [30.0, -6.0, -1.2, 4.2, 1.9, 1.6, -2.0]]
    )
    inside = [_car_points(b, 200, rng) for b in boxes]
    outside = np.array([[5.0, 0.0, -1.9, 0.3], [50.0, 20.0, 0.5, 0.1]], np.float32)
    points = np.concatenate([*inside, outside])
    new_points, new_boxes = shift_frame(points, boxes, DELTA)
    np.testing.assert_allclose(new_boxes[:, 3:6], boxes[:, 3:6] + DELTA)
    np.testing.assert_allclose(new_boxes[:, 2] - new_boxes[:, 5] / 2, boxes[:, 2] - boxes[:, 5] / 2)
    np.testing.assert_array_equal(new_boxes[:, [0, 1, 6]], boxes[:, [0, 1, 6]])
    np.testing.assert_array_equal(new_points[-2:], outside)  # points of no box do not move
    np.testing.assert_array_equal(new_points[:, 3], points[:, 3])  # intensity kept
    for index, box in enumerate(
        boxes
    ):  # each car's points span its new box as they spanned the old
        rows = slice(200 * index, 200 * (index + 1))
        old = _box_frame(points[rows], box) / box[3:6]
        new = _box_frame(new_points[rows], new_boxes[index]) / new_boxes[index, 3:6]
        np.testing.assert_allclose(new, old, atol=2e-5)


def _box_frame(points: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Points `(n, >=3)` in the box's frame with its bottom centre at the origin, `(n, 3)`."""
    d = points[:, :3].astype(np.float64) - [box[0], box[1], box[2] - box[5] / 2]
    cos, sin = np.cos(box[6]), np.sin(box[6])
    return np.stack([cos * d[:, 0] + sin * d[:, 1], -sin * d[:, 0] + cos * d[:, 1], d[:, 2]], 1)


@pytest.fixture
def labeled(tmp_path):
    """Two frames: cars and one pedestrian, each box with its points."""
    rng = np.random.default_rng(1)
    frames, ids, boxes, labels = [], [], [], []
    for frame_index, frame_boxes in enumerate(
        [
            [[10.0, 2.0, -1.1, 4.5, 2.0, 1.7, 0.1], [20.0, -3.0, -1.0, 0.8, 0.7, 1.8, 0.0]],
            [[15.0, 5.0, -1.2, 4.8, 2.1, 1.8, 1.2]],
        ]
    ):
        frame_id = f"{frame_index:06d}"
        frame_boxes = np.asarray(frame_boxes)
        frames.append((frame_id, np.concatenate([_car_points(b, 100, rng) for b in frame_boxes])))
        ids += [frame_id] * len(frame_boxes)
        boxes.append(frame_boxes)
        labels += ["Car", "Pedestrian"][: len(frame_boxes)]
    write_frameset(tmp_path / "data", frames, sensor="waymo")
    write_boxes(tmp_path / "data", BoxTable.from_arrays(ids, np.concatenate(boxes), label=labels))
    return tmp_path / "data", frames


def test_size_norm_stage_shifts_the_cars_and_keeps_everything_else(labeled, tmp_path):
    data, frames = labeled
    out = tmp_path / "sized"
    delta = ",".join(str(v) for v in DELTA)
    result = CliRunner().invoke(main, ["size-norm", "--data", str(data), "--delta", delta,
                                       "--out", str(out)])  # fmt: skip
    assert result.exit_code == 0, result.output
    before, after = read_boxes(data), read_boxes(out)
    cars = before["label"].astype(str) == "Car"
    np.testing.assert_allclose(after.boxes[cars, 3:6], before.boxes[cars, 3:6] + DELTA)
    np.testing.assert_array_equal(after.boxes[~cars], before.boxes[~cars])  # the pedestrian
    assert list(FrameSet(out).frame_ids) == [f for f, _ in frames]
    pedestrian = FrameSet(out).frame(0)[100:]  # the pedestrian's points did not move
    np.testing.assert_array_equal(pedestrian, frames[0][1][100:])
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["outputs"]["counts"]["boxes_shifted"] == 2
    again = CliRunner().invoke(main, ["size-norm", "--data", str(data), "--delta", delta,
                                      "--out", str(out)])  # fmt: skip
    assert again.exit_code == 0 and "up to date" in again.output


def test_size_norm_refuses_a_model_without_a_size_shift_and_a_shift_to_nothing(labeled, tmp_path):
    data, _ = labeled
    model = tmp_path / "model"
    model.mkdir()
    (model / "model.json").write_text(json.dumps({"card": {"size_norm": "none"}}))
    refused = CliRunner().invoke(main, ["size-norm", "--data", str(data), "--like-model",
                                        str(model), "--out", str(tmp_path / "a")])  # fmt: skip
    assert refused.exit_code != 0 and "not trained with a size shift" in refused.output
    assert not (tmp_path / "a").exists()
    crushing = CliRunner().invoke(main, ["size-norm", "--data", str(data), "--delta",
                                         "-0.85,0,0", "--label", "Car", "--label", "Pedestrian",
                                         "--out", str(tmp_path / "b")])  # fmt: skip
    assert crushing.exit_code != 0 and "frame '000000', box row 1" in crushing.output
    assert not (tmp_path / "b").exists()
    both = CliRunner().invoke(
        main, ["size-norm", "--data", str(data), "--out", str(tmp_path / "c")]
    )
    assert both.exit_code != 0 and "exactly one" in both.output
