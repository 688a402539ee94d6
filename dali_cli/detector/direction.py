"""Which way a box faces: the direction classifier's bins, targets and decoding.

The box heads regress (sin 2 yaw, cos 2 yaw), the heading axis: a car turned by pi is the same box
to an IoU, so that regression is well posed but says nothing of where the car's front is. As in
OpenPCDet's SECOND (`dir_offset`, `num_dir_bins` = 2), a two-bin classifier tells the two ends
apart: bin = floor(((yaw - offset) mod 2 pi) / pi). The offset (default pi/4) puts the bins'
edges on the diagonals, away from the headings cars mostly have (along and across the sensor's
axes), so a small error of the axis rarely lands on the wrong side of an edge.

Angles in radians; numpy arrays or torch tensors (then on their device), any shape.
"""

from __future__ import annotations

import math

import numpy as np
import torch

BINS = 2
DEFAULT_OFFSET = math.pi / 4


def direction_bin(yaw, offset: float = DEFAULT_OFFSET):
    """The bin (0 or 1, int64, yaw's shape) of full headings `yaw`: which half turn from `offset`."""
    if isinstance(yaw, torch.Tensor):
        return torch.floor(torch.remainder(yaw - offset, 2 * math.pi) / math.pi).long().clamp(0, 1)
    turned = np.remainder(np.asarray(yaw, np.float64) - offset, 2 * np.pi)
    return np.clip(np.floor(turned / np.pi), 0, 1).astype(np.int64)


def apply_direction(axis_yaw, bins, offset: float = DEFAULT_OFFSET):
    """Full headings in [-pi, pi) from heading axes `axis_yaw` (any angle, read modulo pi) and their
    bins (0/1, same shape): the end of the axis that lies in the bin's half turn."""
    if isinstance(axis_yaw, torch.Tensor):
        half = torch.remainder(axis_yaw - offset, math.pi)  # in [0, pi)
        yaw = half + offset + math.pi * bins.to(axis_yaw.dtype)
        wrapped = torch.remainder(yaw + math.pi, 2 * math.pi) - math.pi
        return torch.where(wrapped >= math.pi, wrapped - 2 * math.pi, wrapped)
    axis_yaw = np.asarray(axis_yaw, np.float64)
    yaw = np.remainder(axis_yaw - offset, np.pi) + offset + np.pi * np.asarray(bins)
    wrapped = np.remainder(yaw + np.pi, 2 * np.pi) - np.pi
    return np.where(wrapped >= np.pi, wrapped - 2 * np.pi, wrapped)


def faces_backwards(yaw, reference_yaw) -> np.ndarray:
    """True where heading `yaw` points more than 90 degrees away from `reference_yaw` (same shape):
    the box's axis may be right, its front is at the other end."""
    return np.cos(np.asarray(yaw, np.float64) - np.asarray(reference_yaw, np.float64)) < 0
