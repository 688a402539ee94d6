"""KITTI's image-box side of the evaluation: predictions' 2D boxes and observation angles from
the camera calibration, the 2D overlaps of predicted and labelled image boxes, and the
threshold they are matched at. KITTI's devkit computes its AOS (and its 2D AP, "bbox") on these
matches, with the observation angle alpha as the heading; evaluate.py applies them when both
tables carry image boxes (`dali eval --calib`), and keeps AOS on the BEV matches otherwise.

Image boxes are `(n, 4)` float64 left, top, right, bottom in pixels; angles in radians.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dali_cli.importers.kitti import (
    DEFAULT_IMAGE_SIZE,
    IGNORE_TYPES,
    Calibration,
    image_boxes,
    lidar_boxes_to_camera,
    observation_angle,
)
from dali_cli.importers.kitti_label import BBOX_COLUMNS as IMAGE_BOX_COLUMNS
from dali_cli.store.artifacts import BoxTable

# the labels whose rows are regions, not objects: their image boxes spare predictions in them
REGION_LABELS = tuple(name.lower() for name in IGNORE_TYPES)
# the 2D overlap a match needs, per class: KITTI's (and OpenPCDet's) "bbox" row, the same in its
# IoU 0.7 and 0.5 settings (Car is matched in the image at 0.7 in both)
IMAGE_MIN_OVERLAP = {"car": 0.7, "van": 0.7, "truck": 0.7, "pedestrian": 0.5, "cyclist": 0.5}


def has_image_boxes(table: BoxTable) -> bool:
    """Whether `table` carries a 2D image box and an observation angle for every box."""
    return all(name in table.columns for name in (*IMAGE_BOX_COLUMNS, "alpha"))


def with_image_boxes(
    table: BoxTable,
    calib_of: Callable[[str], Calibration],
    image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE,
) -> BoxTable:
    """`table` (LiDAR-frame boxes) with each box's image box and alpha through its frame's
    calibration `calib_of(frame_id)`, as `dali export kitti` writes them into label_2: the
    projected 3D corners clipped to the image `image_size` (width, height; pixels), alpha =
    rotation_y minus the viewing ray's angle. A box behind the camera gets a box of no height,
    which KITTI's size filter then ignores."""
    count = len(table)
    bbox = np.zeros((count, 4), np.float64)
    alpha = np.zeros(count, np.float64)
    for frame_id, rows in table.rows_by_frame().items():
        calib = calib_of(frame_id)
        location, hwl, rotation_y = lidar_boxes_to_camera(table.boxes[rows], calib)
        bbox[rows] = image_boxes(location, hwl, rotation_y, calib, image_size)[0]
        alpha[rows] = observation_angle(location, rotation_y)
    columns = {name: bbox[:, k].astype(np.float32) for k, name in enumerate(IMAGE_BOX_COLUMNS)}
    return table.with_columns(**columns, alpha=alpha.astype(np.float32))


def image_overlap(first: np.ndarray, second: np.ndarray, over: str = "union") -> np.ndarray:
    """`(n,)` float64 overlap of the image boxes `first[i]` and `second[i]` (`(n, 4)` each):
    the intersection over their union ("union", IoU) or over `first`'s area ("first", KITTI's
    test of a prediction in a DontCare region), areas as OpenPCDet's eval computes them (no +1
    pixel); 0 where they do not intersect."""
    width = np.minimum(first[:, 2], second[:, 2]) - np.maximum(first[:, 0], second[:, 0])
    height = np.minimum(first[:, 3], second[:, 3]) - np.maximum(first[:, 1], second[:, 1])
    inter = np.clip(width, 0.0, None) * np.clip(height, 0.0, None)
    area_first = (first[:, 2] - first[:, 0]) * (first[:, 3] - first[:, 1])
    area_second = (second[:, 2] - second[:, 0]) * (second[:, 3] - second[:, 1])
    base = area_first if over == "first" else area_first + area_second - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where((inter > 0) & (base > 0), inter / base, 0.0)


def image_min_overlap(class_name: str) -> float:
    """The 2D IoU a prediction of `class_name` must exceed to match in the image."""
    return IMAGE_MIN_OVERLAP.get(class_name.lower(), 0.5)


@dataclass
class ImageMatches:
    """The image-box candidates of a KITTI evaluation: same-frame pairs whose 2D boxes overlap,
    their 2D IoU, and each side's observation angle alpha (the heading AOS weighs)."""

    pairs: tuple[np.ndarray, np.ndarray]  # (E,) prediction and ground-truth indices
    overlap: np.ndarray  # (E,) float64 2D IoU > 0
    pred_alpha: np.ndarray  # (P,) float64 radians
    gt_alpha: np.ndarray  # (G,)
    dont_care: np.ndarray  # (P,) float64 the largest share of a prediction's 2D box in a
    # DontCare region of its frame (KITTI's criterion 0: intersection over the prediction's area)

    def ignored_pred(
        self, ignored_gt: np.ndarray, ignored_pred: np.ndarray, min_overlap: float
    ) -> np.ndarray:
        """`ignored_pred` with the predictions KITTI's devkit does not count as false positives
        on its 2D metric set to ignored: counted ones lying more than `min_overlap` in a
        DontCare region with no candidate ground truth above `min_overlap`. (The devkit also
        spares a prediction that has a candidate but loses it to another: that rare case is
        still a false positive here.)"""
        pred_index, gt_index = self.pairs
        candidate = (self.overlap > min_overlap) & (ignored_gt[gt_index] != -1)
        has_candidate = np.zeros(len(ignored_pred), bool)
        has_candidate[pred_index[candidate]] = True
        spared = (ignored_pred == 0) & (self.dont_care > min_overlap) & ~has_candidate
        return np.where(spared, 1, ignored_pred).astype(ignored_pred.dtype)


def image_matches(
    pred_boxes: np.ndarray,
    gt_boxes: np.ndarray,
    pairs: tuple[np.ndarray, np.ndarray],
    gt_dont_care: np.ndarray,
    pred_alpha: np.ndarray,
    gt_alpha: np.ndarray,
) -> ImageMatches:
    """The image side of an evaluation: image boxes `(P, 4)` and `(G, 4)`, the same-frame index
    pairs `((E,), (E,))`, which ground truths are DontCare regions `(G,)` bool, and the
    observation angles `(P,)`, `(G,)` (radians)."""
    pred_index, gt_index = pairs
    overlap = image_overlap(pred_boxes[pred_index], gt_boxes[gt_index])
    region = gt_dont_care[gt_index]
    dont_care = np.zeros(len(pred_boxes), np.float64)
    np.maximum.at(
        dont_care, pred_index[region],
        image_overlap(pred_boxes[pred_index[region]], gt_boxes[gt_index[region]], "first"),
    )  # fmt: skip
    touching = overlap > 0
    return ImageMatches(
        pairs=(pred_index[touching], gt_index[touching]),
        overlap=overlap[touching],
        pred_alpha=pred_alpha,
        gt_alpha=gt_alpha,
        dont_care=dont_care,
    )
