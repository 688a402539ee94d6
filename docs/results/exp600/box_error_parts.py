"""Diagnostic (reads the target's labels: never a DALI stage): which part of the pseudo boxes
keeps them under 3D IoU 0.7? Pairs each pseudo box with its true car as
docs/results/exp600/label_quality.py does, then, per range band of the true car (0-30, 30-50,
50-80 m from the sensor), prints the share of pairs at 3D IoU >= 0.7 as they are and with one part
of each box replaced by the truth's: the centre along the car, across it, its height z, the
length, width, height and yaw (up to a half turn, the detector's 2-yaw regression), and all sizes.
The part whose fix lifts the share most is where the label-free pseudo labeller loses AP_3D@0.7.

    python docs/results/exp600/box_error_parts.py --truth RUN/data/target --boxes RUN/iter1/pseudo
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "docs" / "results" / "demo7"))

from label_quality import matched_pairs, truth_and_box_dirs  # noqa: E402

from dali_cli.geometry import iou_3d_pairs, wrap_angle  # noqa: E402
from dali_cli.store.artifacts import read_boxes  # noqa: E402

BANDS = ((0.0, 30.0), (30.0, 50.0), (50.0, 80.0))


def fixed(pred: np.ndarray, true: np.ndarray, part: str) -> np.ndarray:
    """pred (P, 7) with `part` taken from true (P, 7); the centre's along / across parts are
    measured in the true car's frame."""
    out = pred.copy()
    c, s = np.cos(true[:, 6]), np.sin(true[:, 6])
    d = pred[:, :2] - true[:, :2]
    along, across = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    if part == "along":
        out[:, 0], out[:, 1] = true[:, 0] - s * across, true[:, 1] + c * across
    elif part == "across":
        out[:, 0], out[:, 1] = true[:, 0] + c * along, true[:, 1] + s * along
    elif part == "yaw":  # the true yaw up to a half turn: the box keeps its own heading
        turn = wrap_angle(pred[:, 6] - true[:, 6])
        out[:, 6] = true[:, 6] + np.where(np.abs(turn) > np.pi / 2, np.pi, 0.0)
    else:
        columns = {"z": [2], "l": [3], "w": [4], "h": [5], "sizes": [3, 4, 5]}[part]
        out[:, columns] = true[:, columns]
    return out


PARTS = ("along", "across", "z", "l", "w", "h", "sizes", "yaw")


def main() -> None:
    truth, box_dirs = truth_and_box_dirs(__doc__)
    print(
        "| boxes | band m | pairs | 3D IoU >= 0.7 | "
        + " | ".join(f"{p} fixed" for p in PARTS)
        + " |"
    )
    print("|---|---|---|---|" + "---|" * len(PARTS))
    for path in box_dirs:
        pred, true = matched_pairs(truth, read_boxes(path))
        distance = np.hypot(true[:, 0], true[:, 1])
        shares = {"as is": iou_3d_pairs(pred, true) >= 0.7}
        shares.update({p: iou_3d_pairs(fixed(pred, true, p), true) >= 0.7 for p in PARTS})
        for low, high in (*BANDS, (0.0, np.inf)):
            band = (distance >= low) & (distance < high)
            name = "all" if high == np.inf else f"{low:.0f}-{high:.0f}"
            cells = " | ".join(f"{shares[p][band].mean():.3f}" for p in PARTS)
            print(
                f"| {path} | {name} | {band.sum()} | {shares['as is'][band].mean():.3f} | {cells} |"
            )


if __name__ == "__main__":
    main()
