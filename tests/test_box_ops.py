"""The torch rotated-box geometry equals dali_cli.geometry's numpy reference: BEV and 3D IoU
(within 1e-6) on random, touching, nested, identical and far-away boxes, and NMS keeps the
same boxes in the same order."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dali_cli import geometry
from dali_cli.detector import box_ops


def random_boxes(rng, n: int, spread_m: float = 6.0, offset_m: float = 0.0) -> np.ndarray:
    boxes = np.empty((n, 7))
    boxes[:, :2] = rng.uniform(-spread_m, spread_m, (n, 2)) + offset_m
    boxes[:, 2] = rng.uniform(0.5, 1.0, n)
    boxes[:, 3:6] = rng.uniform([0.5, 0.4, 0.5], [5.0, 2.5, 2.0], (n, 3))
    boxes[:, 6] = rng.uniform(-np.pi, np.pi, n)
    return boxes


def special_boxes() -> np.ndarray:
    """Identical, nested, edge-sharing, corner-touching, rotated by 90 deg, zero-size boxes."""
    base = np.array([10.0, -3.0, 0.8, 4.0, 1.8, 1.5, 0.3])
    shifted = base.copy()
    shifted[0] += 4.0 * np.cos(0.3)
    shifted[1] += 4.0 * np.sin(0.3)  # shares an edge with base
    nested = base.copy()
    nested[3:5] = [2.0, 1.0]
    turned = base.copy()
    turned[6] += np.pi / 2
    flat = base.copy()
    flat[3] = 0.0
    axis = np.array([0.0, 0.0, 0.0, 2.0, 2.0, 1.0, 0.0])
    corner = np.array([2.0, 2.0, 0.0, 2.0, 2.0, 1.0, 0.0])
    return np.stack([base, base.copy(), shifted, nested, turned, flat, axis, corner])


DEVICES = ["cpu", *(["cuda"] if torch.cuda.is_available() else [])]


@pytest.mark.parametrize("device", DEVICES)
def test_bev_and_3d_iou_match_the_numpy_reference(device):
    rng = np.random.default_rng(0)
    for a, b in [
        (random_boxes(rng, 40), random_boxes(rng, 30)),
        (random_boxes(rng, 20, 2.0, 70.0), random_boxes(rng, 20, 2.0, 70.0)),  # far out
        (special_boxes(), special_boxes()),
    ]:
        ta, tb = torch.from_numpy(a).to(device), torch.from_numpy(b).to(device)
        bev = box_ops.bev_iou(ta, tb).cpu().numpy()
        assert np.abs(bev - geometry.bev_iou(a, b)).max() < 1e-6
        assert np.abs(box_ops.iou_3d(ta, tb).cpu().numpy() - geometry.iou_3d(a, b)).max() < 1e-6
        assert (bev > 0.05).any()  # the cases do overlap
    pairs = box_ops.bev_intersection_pairs(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    assert np.abs(pairs - geometry.bev_intersection_pairs(a, b)).max() < 1e-6


@pytest.mark.parametrize("device", DEVICES)
def test_nms_keeps_what_the_numpy_nms_keeps(device):
    rng = np.random.default_rng(1)
    for n in (0, 1, 60):
        boxes = random_boxes(rng, n, 5.0)
        scores = rng.random(n)
        scores[: n // 3] = 0.5  # ties keep the earlier index first
        for threshold in (0.01, 0.1, 0.5):
            expected = geometry.nms_bev(boxes, scores, threshold)
            kept = box_ops.nms_bev(
                torch.from_numpy(boxes).to(device), torch.from_numpy(scores).to(device), threshold
            )
            assert kept.dtype == torch.int64 and np.array_equal(kept.cpu().numpy(), expected)


def test_iou_head_targets_on_the_device_match_the_numpy_ones():
    from dali_cli.detector.config import DetectorConfig
    from dali_cli.detector.targets import build_targets, cell_iou_targets, device_peak_targets

    rng = np.random.default_rng(2)
    config = DetectorConfig()
    objects = [random_boxes(rng, 6, 8.0, 30.0), random_boxes(rng, 3, 8.0, 30.0)]
    targets = build_targets(objects, config)
    noisy = torch.from_numpy(targets.boxes + rng.normal(0, 0.2, targets.boxes.shape))
    host = cell_iou_targets(noisy, targets, targets.mask, on_device=False)
    device = cell_iou_targets(noisy, targets, targets.mask, on_device=True)
    assert host.dtype == device.dtype == torch.float32 and (host > 0.3).sum() > 5
    assert (host - device).abs().max() < 1e-6
    peaks = torch.from_numpy(random_boxes(rng, 2 * 20, 8.0, 30.0).reshape(2, 20, 7))
    expected = [geometry.iou_3d(peaks[b].numpy(), objects[b]).max(axis=1) for b in range(2)]
    found = device_peak_targets(peaks, objects, 2, 20).numpy()
    assert np.abs(found - np.stack(expected)).max() < 1e-6
