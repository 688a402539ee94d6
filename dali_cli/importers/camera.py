"""A virtual KITTI camera for LiDAR-frame boxes: the label_2 fields KITTI's difficulty filters
read (2D box, truncation, occlusion level) and alpha, computed the way KITTI defines them.

The camera is KITTI's left colour camera (P2) at KITTI's place relative to the LiDAR, taken
from the calib of the real KITTI frame 000008 (tests/fixtures/real/kitti/training/calib): about
0.27 m in front of the LiDAR and 0.08 m below it, looking along +x. Every sensor profile gets
this same camera at its own origin (the camera rides with the LiDAR, so on a sensor mounted
higher than KITTI's the camera is higher too). `dali synth` labels carry these columns so that
`dali eval --protocol kitti` gives easy / moderate / hard on synthetic data.
"""

from __future__ import annotations

import numpy as np

from dali_cli.geometry import box_corners
from dali_cli.importers.kitti import (
    DEFAULT_IMAGE_SIZE,
    Calibration,
    lidar_boxes_to_camera,
    observation_angle,
)

# KITTI object calib of training frame 000008 (any KITTI frame's differs by millimetres)
KITTI_P2 = np.array(
    [
        [7.215377e02, 0.0, 6.095593e02, 4.485728e01],
        [0.0, 7.215377e02, 1.728540e02, 2.163791e-01],
        [0.0, 0.0, 1.0, 2.745884e-03],
    ]
)
KITTI_R0_RECT = np.array(
    [
        [9.999238848686e-01, 9.837759658694e-03, -7.445048075169e-03],
        [-9.869795292616e-03, 9.999421238899e-01, -4.278459120542e-03],
        [7.402527146041e-03, 4.351614043117e-03, 9.999631047249e-01],
    ]
)
KITTI_TR_VELO_TO_CAM = np.array(
    [
        [7.533744908869e-03, -9.999713897705e-01, -6.166020175442e-04, -4.069766029716e-03],
        [1.480249036103e-02, 7.280732970685e-04, -9.998902082443e-01, -7.631617784500e-02],
        [9.998620748520e-01, 7.523790001869e-03, 1.480755023658e-02, -2.717806100845e-01],
    ]
)
NOMINAL_CALIB = Calibration(P2=KITTI_P2, R0_rect=KITTI_R0_RECT, Tr_velo_to_cam=KITTI_TR_VELO_TO_CAM)
IMAGE_SIZE = DEFAULT_IMAGE_SIZE  # (1242, 375) width, height in pixels
NEAR_PLANE_M = 0.1  # box parts closer to the camera plane than this are cut off before projecting

# KITTI's occlusion levels (0 fully visible, 1 partly, 2 largely occluded) were set by annotators
# looking at the image; here they come from the share of a car's LiDAR rays blocked by something
# nearer. Below 10% is a pole or a mirror's sliver, which an annotator calls fully visible; from
# half hidden on a car is "largely" occluded.
PARTLY_OCCLUDED_FROM = 0.1
LARGELY_OCCLUDED_FROM = 0.5

_EDGES = np.array(
    [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
     [0, 4], [1, 5], [2, 6], [3, 7]]
)  # fmt: skip  # the 12 edges of geometry.box_corners' order (bottom face, top face)


def box_pixels(
    boxes: np.ndarray, calib: Calibration = NOMINAL_CALIB, near_m: float = NEAR_PLANE_M
) -> tuple[np.ndarray, np.ndarray]:
    """Image points of each box cut by the near plane (rectified depth >= `near_m`).

    boxes : (N, 7) float LiDAR-frame boxes (x, y, z centre, l, w, h in metres, yaw in rad).
    Returns pixels `(N, 20, 2)` float64 (u right, v down) of the 8 corners and of the 12 edges'
    crossings of the near plane, and valid `(N, 20)` bool: the corners in front of the plane and
    the crossings that exist. Their hull is the projection of the part of the box in front.
    """
    corners = box_corners(boxes)  # (N, 8, 3) LiDAR frame
    count = len(corners)
    rect = calib.lidar_to_rect(corners.reshape(-1, 3)).reshape(count, 8, 3)  # (N, 8, 3)
    start, end = rect[:, _EDGES[:, 0]], rect[:, _EDGES[:, 1]]  # (N, 12, 3)
    gap_start, gap_end = start[..., 2] - near_m, end[..., 2] - near_m  # (N, 12)
    crosses = gap_start * gap_end < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(crosses, gap_start / (gap_start - gap_end), 0.0)  # (N, 12)
    crossing = start + t[..., None] * (end - start)  # (N, 12, 3)
    points = np.concatenate([rect, crossing], axis=1)  # (N, 20, 3)
    valid = np.concatenate([rect[..., 2] >= near_m, crosses], axis=1)  # (N, 20)
    pixels, _ = calib.rect_to_image(np.where(valid[..., None], points, 1.0).reshape(-1, 3))
    return pixels.reshape(count, 20, 2), valid


def image_boxes_2d(
    boxes: np.ndarray,
    calib: Calibration = NOMINAL_CALIB,
    image_size: tuple[int, int] = IMAGE_SIZE,
    near_m: float = NEAR_PLANE_M,
) -> tuple[np.ndarray, np.ndarray]:
    """2D boxes of LiDAR-frame boxes `(N, 7)` seen by the camera, before and after clipping.

    Returns full `(N, 4)` float64 left, top, right, bottom in pixels of the projected part of the
    box in front of the near plane (may extend past the image), and clipped `(N, 4)` float64: the
    same clipped to the image, [0, width - 1] x [0, height - 1]. A box wholly behind the near
    plane gets all zeros in both.
    """
    pixels, valid = box_pixels(boxes, calib, near_m)  # (N, 20, 2), (N, 20)
    low = np.where(valid[..., None], pixels, np.inf).min(axis=1)  # (N, 2)
    high = np.where(valid[..., None], pixels, -np.inf).max(axis=1)  # (N, 2)
    full = np.c_[low, high]  # (N, 4) left, top, right, bottom
    full[~valid.any(axis=1)] = 0.0
    width, height = image_size
    limit = np.array([width - 1, height - 1, width - 1, height - 1], np.float64)
    clipped = np.clip(full, 0.0, limit)
    return full, clipped


def truncation(full: np.ndarray, clipped: np.ndarray) -> np.ndarray:
    """KITTI truncation `(N,)` float64 in [0, 1]: the share of the 2D box `full` `(N, 4)` outside
    the image, 1 - area(clipped) / area(full); 1 when nothing is in the image."""
    area_full = (full[:, 2] - full[:, 0]) * (full[:, 3] - full[:, 1])
    area_clipped = np.maximum(clipped[:, 2] - clipped[:, 0], 0.0) * np.maximum(
        clipped[:, 3] - clipped[:, 1], 0.0
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(area_full > 0, area_clipped / area_full, 0.0)
    return np.clip(1.0 - share, 0.0, 1.0)


def occlusion_level(fraction: np.ndarray) -> np.ndarray:
    """KITTI occlusion levels `(N,)` int32 (0 fully visible, 1 partly, 2 largely occluded) of
    blocked-ray fractions `(N,)` in [0, 1] (see PARTLY_OCCLUDED_FROM, LARGELY_OCCLUDED_FROM)."""
    fraction = np.asarray(fraction, np.float64)
    return (
        (fraction >= PARTLY_OCCLUDED_FROM).astype(np.int32)
        + (fraction >= LARGELY_OCCLUDED_FROM).astype(np.int32)
    ).reshape(-1)


def kitti_label_columns(
    boxes: np.ndarray,
    occlusion: np.ndarray,
    calib: Calibration = NOMINAL_CALIB,
    image_size: tuple[int, int] = IMAGE_SIZE,
) -> dict[str, np.ndarray]:
    """The KITTI label columns of docs/INTERFACES.md for LiDAR-frame boxes `(N, 7)` with blocked-ray
    fractions `occlusion` `(N,)`: truncated float32, occluded int32, alpha float64 (rad, as
    `dali export kitti` computes it) and bbox_left/top/right/bottom float32 (pixels, clipped).

    Pure geometry of the boxes: no randomness, so adding the columns changes nothing else.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    full, clipped = image_boxes_2d(boxes, calib, image_size)
    location, _, rotation_y = lidar_boxes_to_camera(boxes, calib)
    return {
        "truncated": truncation(full, clipped).astype(np.float32),
        "occluded": occlusion_level(occlusion),
        "alpha": np.asarray(observation_angle(location, rotation_y), np.float64),
        "bbox_left": clipped[:, 0].astype(np.float32),
        "bbox_top": clipped[:, 1].astype(np.float32),
        "bbox_right": clipped[:, 2].astype(np.float32),
        "bbox_bottom": clipped[:, 3].astype(np.float32),
    }
