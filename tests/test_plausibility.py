"""Plausibility limits of boxes (dali_cli.labels.plausibility) and the training-label reader that refuses
implausible labels (pretrain with l = 1e30 used to end in numpy's "negative dimensions")."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.detector import DetectorConfig, load_labeled
from dali_cli.labels import plausibility
from dali_cli.sensors import get_profile
from dali_cli.store.artifacts import ArtifactError, BoxTable, write_boxes, write_frameset

CAR = [12.0, 3.0, -0.9, 3.9, 1.6, 1.5, 0.4]


def test_limits_accept_real_objects_and_refuse_corrupt_ones():
    kitti = get_profile("kitti")
    assert plausibility.max_center_distance_m(kitti.max_range_m) == 2 * kitti.max_range_m
    real = np.array(
        [
            CAR,
            [40.0, -5.0, 0.2, 18.75, 2.55, 4.0, 3.1],  # articulated bus
            [8.0, 1.0, -1.0, 0.5, 0.6, 1.8, 0.0],  # pedestrian
            [230.0, 0.0, 0.0, 3.9, 1.6, 1.5, 0.0],  # beyond the 120 m range, inside 2x
            [12.0, 3.0, -0.9, 1.6, 3.9, 1.5, 1.97],  # l and w swapped with the yaw
        ]
    )
    assert plausibility.plausible(real, kitti.max_range_m).all()
    assert all(plausibility.problem(box, kitti.max_range_m) is None for box in real)
    corrupt = {
        "'l' = 1e+06 m": [12.0, 3.0, -0.9, 1e6, 1.6, 1.5, 0.0],
        "'w' = 1e+30 m": [12.0, 3.0, -0.9, 3.9, 1e30, 1.5, 0.0],
        "'h' = 12 m": [12.0, 3.0, -0.9, 3.9, 1.6, 12.0, 0.0],
        "'l' = 0.001 m": [12.0, 3.0, -0.9, 0.001, 1.6, 1.5, 0.0],
        "'yaw' is nan": [12.0, 3.0, -0.9, 3.9, 1.6, 1.5, np.nan],
        "'x' is inf": [np.inf, 3.0, -0.9, 3.9, 1.6, 1.5, 0.0],
        "250 m from the sensor, beyond 240 m": [250.0, 0.0, 0.0, 3.9, 1.6, 1.5, 0.0],
        "1e+06 m from the sensor": [0.0, 0.0, 1e6, 3.9, 1.6, 1.5, 0.0],
    }
    boxes = np.array(list(corrupt.values()))
    assert not plausibility.plausible(boxes, kitti.max_range_m).any()
    for expected, box in corrupt.items():
        assert expected in plausibility.problem(np.array(box), kitti.max_range_m)
    # without a profile the default range applies (2 x 250 m)
    assert plausibility.plausible(np.array([[450.0, 0, 0, 3.9, 1.6, 1.5, 0]])).all()
    assert plausibility.plausible(np.zeros((0, 7))).shape == (0,)


def labeled_set(directory, boxes, labels):
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(2, 40, (500, 2)), rng.uniform(-1.7, 0, 500), np.full(500, 0.3)]
    write_frameset(directory, [("000000", points.astype(np.float32))], sensor="kitti")
    write_boxes(
        directory, BoxTable.from_arrays(["000000"] * len(boxes), np.array(boxes), label=labels)
    )


@pytest.mark.parametrize(
    "bad, message",
    [
        ([12.0, 3.0, -0.9, 1e30, 1.6, 1.5, 0.0], "field 'l' = 1e+30 m"),
        ([12.0, 3.0, -0.9, 3890.0, 1620.0, 1530.0, 0.0], "field 'l' = 3890 m"),  # millimetres
        ([1e6, 3.0, -0.9, 3.9, 1.6, 1.5, 0.0], "1e+06 m from the sensor"),
    ],
)
def test_training_labels_outside_the_limits_are_an_error_naming_the_row(tmp_path, bad, message):
    data = tmp_path / "source"
    data.mkdir()
    # a DontCare placeholder (zero size) is not a target and not checked
    labeled_set(data, [CAR, bad, np.zeros(7)], ["Car", "Car", "DontCare"])
    with pytest.raises(ArtifactError, match="row 1 \\(frame '000000'\\)") as caught:
        load_labeled(data, DetectorConfig())
    assert message in str(caught.value) and "boxes.parquet" in str(caught.value)
    assert "in metres" in str(caught.value)
    out = tmp_path / "model"
    result = CliRunner().invoke(
        main, ["pretrain", "--source", str(data), "--epochs", "1", "--out", str(out)]
    )
    assert result.exit_code == 1 and message in result.output and "row 1" in result.output
    assert not out.exists()


def test_plausible_training_labels_load(tmp_path):
    labeled_set(tmp_path, [CAR, np.zeros(7)], ["Car", "DontCare"])
    data = load_labeled(tmp_path, DetectorConfig(), min_points=0)
    assert data.num_boxes == 1
