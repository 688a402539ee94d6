"""How well predicted boxes face their cars' way: the heading weights of KITTI's AOS and Waymo's
APH, nuScenes' mean orientation error and the share of true positives facing backwards.

AP_BEV and AP_3D cannot see a heading error of pi (a box turned by half a turn has the same
overlap); each dataset's own metric does. Every function takes headings in radians and is pure
numpy; the matching they are applied to is the evaluator's (evaluate.py). Definitions and sources:
docs/evaluation.md.
"""

from __future__ import annotations

import numpy as np

from dali_cli import geometry

HEADING_METRICS = ("aos", "aph")


def heading_error(pred_yaw: np.ndarray, gt_yaw: np.ndarray) -> np.ndarray:
    """|pred - gt| wrapped to [0, pi] `(n,)` float64 (radians)."""
    delta = geometry.wrap_angle(np.asarray(pred_yaw, np.float64) - np.asarray(gt_yaw, np.float64))
    return np.abs(delta)


def heading_weight(pred_yaw: np.ndarray, gt_yaw: np.ndarray, kind: str) -> np.ndarray:
    """`(n,)` float64 in [0, 1], the weight a true positive counts with:

    - "aos", KITTI's orientation similarity (devkit, Geiger et al. 2012): (1 + cos dtheta) / 2;
    - "aph", Waymo's heading accuracy (Sun et al. 2020): 1 - |dtheta| / pi, dtheta in [0, pi].

    Both are 1 for the right heading, 1/2 at a quarter turn and 0 for a box facing backwards."""
    if kind == "aos":
        delta = np.asarray(pred_yaw, np.float64) - np.asarray(gt_yaw, np.float64)
        return (1.0 + np.cos(delta)) / 2.0
    if kind == "aph":
        return 1.0 - heading_error(pred_yaw, gt_yaw) / np.pi
    raise ValueError(f"unknown heading metric {kind!r} (choose from {', '.join(HEADING_METRICS)})")


def heading_summary(pred_yaw: np.ndarray, gt_yaw: np.ndarray) -> dict:
    """Of matched true positives' headings `(n,)`: their count, nuScenes' mean orientation error
    (AOE, radians, the mean of |dtheta| in [0, pi]; None for n = 0), how many face backwards
    (|dtheta| > pi/2) and that share."""
    error = heading_error(pred_yaw, gt_yaw)
    backwards = int(np.sum(error > np.pi / 2))
    count = len(error)
    return {
        "tp": count,
        "aoe_rad": round(float(error.mean()), 4) if count else None,
        "backwards": backwards,
        "backwards_share": round(backwards / count, 4) if count else None,
    }
