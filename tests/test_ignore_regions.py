"""Ignore regions (dali_cli.detector.ignore): `pseudo-label --ignore-min` writes the boxes scored
under the cut as DontCare, `retrain --ignore-label DontCare` teaches neither car nor background
there: no heatmap negatives in their cells, no IoU-head or refiner samples centred in them."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from dali_cli.detector import Augmentation, DetectorConfig
from dali_cli.detector.augment import ObjectDatabase, sample_ground_truth
from dali_cli.detector.data import LabeledFrames, augmented_sample
from dali_cli.detector.ignore import (
    IGNORE_LABEL,
    MARGIN_M,
    ignored_cells,
    ignored_centres,
    inside_footprints,
)
from dali_cli.detector.targets import build_targets, focal_loss, peak_iou_loss

CONFIG = DetectorConfig.from_dict(
    dict(x_range_m=[0.0, 25.6], y_range_m=[-12.8, 12.8], pfn_channels=8,
         block_channels=[8, 16, 16], block_layers=[1, 1, 1], up_channels=8, head_channels=8)
)  # fmt: skip
CAR = np.array([10.0, 3.0, 0.8, 4.0, 1.8, 1.5, 0.0])
REGION = np.array([18.0, -5.0, 0.8, 4.0, 1.8, 1.5, np.pi / 2])  # turned a quarter: long along y


def cell_centre(x: float, y: float) -> tuple[int, int]:
    """(row, col) of the head cell holding (x, y)."""
    return (
        int((y - CONFIG.y_range_m[0]) // CONFIG.cell_m),
        int((x - CONFIG.x_range_m[0]) // CONFIG.cell_m),
    )


def test_footprints_are_rotated_rectangles_grown_by_the_margin():
    xy = np.array([[18.0, -5.0 + 1.9], [18.0 + 0.85, -5.0], [18.0 + 1.5, -5.0], [18.0, -7.6]])
    assert inside_footprints(xy, REGION[None]).tolist() == [True, True, False, False]
    assert inside_footprints(xy, REGION[None], margin_m=0.7).tolist() == [True, True, True, True]
    assert not inside_footprints(xy, np.zeros((0, 7))).any()
    centres = np.array([REGION, CAR])
    assert ignored_centres(centres, REGION[None]).tolist() == [True, False]
    assert ignored_centres(centres, None).tolist() == [False, False]


def test_ignored_cells_cover_the_footprint_and_nothing_far():
    mask = ignored_cells(REGION[None], CONFIG)
    assert mask.shape == CONFIG.head_size
    assert mask[cell_centre(18.0, -5.0)] and mask[cell_centre(18.0, -6.9)]  # along its length
    assert not mask[cell_centre(18.0 + 0.9 + MARGIN_M + 0.7, -5.0)]  # beyond its width + margin
    assert not mask[cell_centre(10.0, 3.0)]
    area = mask.sum() * CONFIG.cell_m**2
    grown = (4.0 + 2 * MARGIN_M) * (1.8 + 2 * MARGIN_M)
    assert 0.7 * grown < area < 1.3 * grown
    outside = REGION.copy()
    outside[0] = -30.0  # beyond the grid: nothing marked, no error
    assert not ignored_cells(outside[None], CONFIG).any()


def test_build_targets_marks_ignore_cells_only_when_there_are_regions():
    plain = build_targets([CAR[None]], CONFIG)
    assert plain.ignore_cells is None and plain.ignore_boxes is None
    empty = build_targets([CAR[None]], CONFIG, [np.zeros((0, 7))])
    assert empty.ignore_cells is None  # the batch has no region: the losses as before
    targets = build_targets([CAR[None], CAR[None]], CONFIG, [REGION[None], np.zeros((0, 7))])
    assert targets.ignore_cells.shape == (2, 1, *CONFIG.head_size)
    assert targets.ignore_cells[0, 0][cell_centre(18.0, -5.0)] == 1
    assert targets.ignore_cells[1].sum() == 0
    assert torch.equal(targets.heatmap, plain.heatmap.repeat(2, 1, 1, 1))  # targets unchanged


def test_focal_loss_drops_negatives_in_ignore_cells_and_keeps_positives():
    targets = build_targets([CAR[None]], CONFIG, [REGION[None]])
    logits = torch.full(targets.heatmap.shape, -12.0)  # background terms ~0 ...
    row, col = cell_centre(18.0, -5.0)
    logits[0, 0, row - 1 : row + 2, col - 1 : col + 2] = (
        3.0  # ... but a confident blob in the region
    )
    with_region = focal_loss(logits, targets.heatmap, targets.ignore_cells)
    without = focal_loss(logits, targets.heatmap)
    blob = torch.zeros_like(logits)
    blob[0, 0, row - 1 : row + 2, col - 1 : col + 2] = 1
    # ignoring the region removes exactly the blob's negative terms
    only_outside = focal_loss(logits, targets.heatmap, blob)
    assert with_region < without and with_region == pytest.approx(float(only_outside), rel=1e-5)
    everything = torch.ones_like(logits)  # every cell ignored: the positive term remains
    positive = focal_loss(logits, targets.heatmap, everything)
    prob = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    at_peak = targets.heatmap.eq(1)
    expected = -(torch.log(prob) * (1 - prob).pow(2))[at_peak].sum() / at_peak.sum()
    assert float(positive) == pytest.approx(float(expected), rel=1e-5) and positive > 0


def peak_maps(x: float, y: float) -> dict[str, torch.Tensor]:
    """Head maps with one strong peak at (x, y) decoding a car-sized box there."""
    h, w = CONFIG.head_size
    heat = torch.full((1, 1, h, w), -6.0)
    row, col = cell_centre(x, y)
    heat[0, 0, row, col] = 4.0
    offset = torch.full((1, 2, h, w), 0.5)
    z = torch.full((1, 1, h, w), 0.8)
    size = torch.log(torch.tensor([4.0, 1.8, 1.5])).view(1, 3, 1, 1).expand(1, 3, h, w).clone()
    rot = torch.stack([torch.zeros(h, w), torch.ones(h, w)])[None]  # sin 2yaw, cos 2yaw
    return {"heatmap": heat, "offset": offset, "z": z, "size": size, "rot": rot,
            "iou": torch.full((1, 1, h, w), 2.0)}  # fmt: skip


def test_peak_iou_loss_leaves_out_peaks_in_ignore_regions_only():
    config = DetectorConfig.from_dict({**CONFIG.to_dict(), "iou_peak_cells": 1})
    maps = peak_maps(18.0, -5.0)  # the one peak sits in the region, on no car
    plain = peak_iou_loss(maps, build_targets([CAR[None]], config), config)
    ignored = peak_iou_loss(maps, build_targets([CAR[None]], config, [REGION[None]]), config)
    assert plain > 0.5 and ignored == 0.0  # an IoU of 1 predicted on background, or nothing
    on_car = peak_maps(10.0, 3.0)  # a peak on the car inside a region is still trained
    car_region = CAR.copy()
    kept = peak_iou_loss(on_car, build_targets([CAR[None]], config, [car_region[None]]), config)
    assert kept == pytest.approx(
        float(peak_iou_loss(on_car, build_targets([CAR[None]], config), config))
    )


def test_refine_loss_leaves_out_proposals_in_ignore_regions():
    from dali_cli.detector.model import PillarCenterNet
    from dali_cli.detector.refine import refine_loss

    config = DetectorConfig.from_dict({**CONFIG.to_dict(), "refine": True})
    torch.manual_seed(0)
    refiner = PillarCenterNet(config).refiner
    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform([16, -7, 0, 0], [20, -3, 1.5, 1], (200, 4))]).astype(
        np.float32
    )
    proposal = REGION[None]  # a proposal on the region's clutter, no target box in the frame

    def losses(ignore):
        return refine_loss(refiner, [points], [proposal], [np.zeros((0, 7))], config,
                           np.random.default_rng(1), ignore)  # fmt: skip

    _, iou_plain = losses(None)
    _, iou_ignored = losses([REGION[None]])
    assert iou_plain > 0 and iou_ignored == 0.0


def frames_with(boxes: np.ndarray, ignore: np.ndarray | None) -> LabeledFrames:
    rng = np.random.default_rng(3)
    points = rng.uniform([0, -12, 0, 0], [25, 12, 2, 1], (3000, 4)).astype(np.float32)
    return LabeledFrames("toy", "kitti", 1.73, ["000"], [points], [boxes],
                         ignore=None if ignore is None else [ignore])  # fmt: skip


def test_augmented_ignore_regions_follow_the_frame_and_leave_its_draws_alone():
    settings = Augmentation(gt_sampling=False, object_noise=False, scaling=(0.9, 1.1))
    plain = augmented_sample(frames_with(CAR[None], None), 0, np.random.default_rng(5), settings)
    sample = augmented_sample(
        frames_with(CAR[None], REGION[None]), 0, np.random.default_rng(5), settings
    )
    assert np.array_equal(plain.points, sample.points) and np.array_equal(plain.boxes, sample.boxes)
    assert plain.ignore.shape == (0, 7) and sample.ignore.shape == (1, 7)
    car, region = sample.boxes[0], sample.ignore[0]
    factor = car[3] / CAR[3]  # the frame's scaling
    assert np.hypot(*(region[:2] - car[:2])) == pytest.approx(
        factor * np.hypot(*(REGION[:2] - CAR[:2]))
    )
    assert region[3] == pytest.approx(factor * REGION[3])
    turn = np.cos(2 * (region[6] - car[6]))  # flip and rotation keep the two yaws' relation
    assert turn == pytest.approx(np.cos(2 * (REGION[6] - CAR[6])))


def test_ground_truth_sampling_pastes_no_car_into_an_ignore_region():
    rng = np.random.default_rng(0)
    candidate = REGION.copy()
    candidate[6] = 0.0
    database = ObjectDatabase(
        boxes=candidate[None], points=rng.uniform(-1, 1, (20, 4)).astype(np.float32) + [18, -5, 1, 0],
        offsets=np.array([0, 20]),
    )  # fmt: skip
    points = np.zeros((0, 4), np.float32)
    _, pasted = sample_ground_truth(points, np.zeros((0, 7)), database, rng, 5)
    assert len(pasted) == 1
    _, blocked = sample_ground_truth(
        points, np.zeros((0, 7)), database, np.random.default_rng(0), 5, blocked=REGION[None]
    )
    assert len(blocked) == 0


def test_load_labeled_reads_ignore_labels_as_regions(tmp_path):
    from dali_cli.detector import load_labeled
    from dali_cli.store.artifacts import BoxTable, write_boxes, write_frameset

    rng = np.random.default_rng(1)
    points = rng.uniform([5, -10, -1.7, 0], [25, 10, 0.5, 1], (4000, 4)).astype(np.float32)
    write_frameset(tmp_path, [("000", points)], sensor="kitti")
    car = CAR.copy()
    car[2] -= 1.73  # sensor frame
    region = REGION.copy()
    region[2] -= 1.73
    placeholder = np.zeros(7)  # a DontCare row without a size (KITTI's placeholder): no region
    write_boxes(tmp_path, BoxTable.from_arrays(
        ["000"] * 3, np.stack([car, region, placeholder]), label=["Car", IGNORE_LABEL, IGNORE_LABEL]
    ))  # fmt: skip
    plain = load_labeled(tmp_path, CONFIG)
    assert plain.ignore is None and len(plain.boxes[0]) == 1
    data = load_labeled(tmp_path, CONFIG, ignore_labels=(IGNORE_LABEL,))
    assert len(data.boxes[0]) == 1 and data.ignore[0].shape == (1, 7)
    np.testing.assert_allclose(data.ignore[0][0], REGION)  # ground frame, like the boxes


class BandDetector:
    """Three boxes per frame, scored 0.9, 0.45 and 0.2, far apart."""

    def predict(self, points_list, scale=1.0, mount_height_m=None):
        boxes = np.array([[10.0, -6.0, -0.9, 3.9, 1.6, 1.5, 0.0],
                          [10.0, 0.0, -0.9, 3.9, 1.6, 1.5, 0.0],
                          [10.0, 6.0, -0.9, 3.9, 1.6, 1.5, 0.0]])  # fmt: skip
        return [(boxes.copy(), np.array([0.9, 0.45, 0.2], np.float32)) for _ in points_list]


def test_pseudo_label_writes_the_band_as_dontcare_and_leaves_the_cars_as_they_were(
    tmp_path, monkeypatch
):
    from stub_stage import pseudo_label_cli, write_stub_inputs

    import stages.pseudo_label
    from dali_cli.store.artifacts import read_boxes

    rng = np.random.default_rng(2)
    clouds = [rng.uniform([0, -20, -1.7, 0], [40, 20, 0.2, 1], (3000, 4)).astype(np.float32)]
    target, model = write_stub_inputs(tmp_path, clouds * 2)
    monkeypatch.setattr(stages.pseudo_label, "load_detector", lambda _: BandDetector())
    runs = {"plain": [], "band": ["--ignore-min", "0.3"]}
    for name, options in runs.items():
        result = pseudo_label_cli(model, target, tmp_path / name, "--score-min", "0.4", *options)
        assert result.exit_code == 0, result.output
    plain, band = read_boxes(tmp_path / "plain"), read_boxes(tmp_path / "band")
    labels = np.asarray(band["label"]).astype(str)
    cars = band.select(np.flatnonzero(labels == "Car"))
    np.testing.assert_array_equal(cars.boxes, plain.boxes)
    assert (np.asarray(cars["score"]) >= 0.4).all() and len(cars) == 4
    assert (labels != IGNORE_LABEL).all()  # 0.2 is under --ignore-min 0.3: not written at all
    manifest = json.loads((tmp_path / "band" / "manifest.json").read_text())
    assert manifest["params"]["ignore_min"] == 0.3
    assert (
        "ignore_min" not in json.loads((tmp_path / "plain" / "manifest.json").read_text())["params"]
    )
    assert manifest["outputs"]["counts"]["boxes_ignore"] == 0

    wide = pseudo_label_cli(
        model, target, tmp_path / "wide", "--score-min", "0.4", "--ignore-min", "0.1"
    )
    assert wide.exit_code == 0, wide.output
    table = read_boxes(tmp_path / "wide")
    labels = np.asarray(table["label"]).astype(str)
    ignored = table.select(np.flatnonzero(labels == IGNORE_LABEL))
    np.testing.assert_allclose(np.sort(np.asarray(ignored["score"])), [0.2, 0.2], atol=1e-6)
    np.testing.assert_allclose(ignored.boxes[:, 1], [6.0, 6.0])  # as detected, not fitted
    summary = json.loads((tmp_path / "wide" / "summary.json").read_text())
    assert summary["boxes"] == 4 and summary["boxes_ignore"] == 2  # cars only in the summary

    bad = pseudo_label_cli(
        model, target, tmp_path / "bad", "--score-min", "0.4", "--ignore-min", "0.5"
    )
    assert bad.exit_code != 0 and "ignore" in bad.output and not (tmp_path / "bad").exists()
