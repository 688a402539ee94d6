"""How much of a paired AP_R40 difference is the last recall positions.

AP_R40 = Σ_k p(k/40) / 40 over the recall positions k = 1..40, p the interpolated precision, 0 at
positions above the row's maximum recall. Δ = AP(b) − AP(a) splits into the positions both rows
reach (a better precision at the same recall) and those only one reaches (the maximum recall at
the IoU crossing a k/40 boundary: one position is worth p/40, about 2 AP at p ≈ 0.85).

  python docs/results/exp600/recall_steps.py A/metrics.json B/metrics.json [3d|bev] [band]
"""

from __future__ import annotations

import json
import sys

import numpy as np


def curve(path: str, kind: str, band: str) -> tuple[np.ndarray, float]:
    """(40,) interpolated precision at the recall positions 1/40 .. 40/40 (Car, first IoU) and
    the maximum recall reached (at the lowest sampled score threshold)."""
    block = json.load(open(path))["Car"]["curves"][kind][band]
    return np.asarray(block["precision"][1:41]), float(max(block["recall"], default=0.0))


def main() -> None:
    a_path, b_path = sys.argv[1], sys.argv[2]
    kind = sys.argv[3] if len(sys.argv) > 3 else "3d"
    band = sys.argv[4] if len(sys.argv) > 4 else "all"
    (a, recall_a), (b, recall_b) = curve(a_path, kind, band), curve(b_path, kind, band)
    both = (a > 0) & (b > 0)
    shared = float((b[both] - a[both]).sum() / 40 * 100)
    tail = float((b[~both] - a[~both]).sum() / 40 * 100)
    print(f"AP {a.sum() / 40 * 100:.2f} -> {b.sum() / 40 * 100:.2f}: Δ {shared + tail:+.2f} = "
          f"{shared:+.2f} at the {int(both.sum())} positions both reach "
          f"+ {tail:+.2f} at the positions one reaches ({int((a > 0).sum())} vs {int((b > 0).sum())}; "
          f"maximum recall {recall_a:.3f} vs {recall_b:.3f})")  # fmt: skip


if __name__ == "__main__":
    main()
