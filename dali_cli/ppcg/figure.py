"""A PNG of a few boxes before and after RC and CF, bird's-eye and side views (paper Fig. 9).

Reads the outputs of `dali ppcg-rc` and `dali ppcg-cf` (run on the same box table) and the target
frame set their manifests name. Points are drawn in each box's own frame (x along the heading),
so every panel of a row shares axes. For `dali report`: `plot_ppcg_examples(rc_dir, cf_dir, png)`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dali_cli.geometry import wrap_angle
from dali_cli.ppcg.fitting import sensor_to_model
from dali_cli.store.artifacts import ArtifactError, FrameSet, read_boxes
from dali_cli.store.manifest import read_input_manifest

_MARGIN_M = 0.6  # drawn around each box


def _target_of(stage_dir: Path) -> Path:
    manifest = read_input_manifest(stage_dir) or {}
    records = manifest.get("inputs", {}).get("target") or []
    if not records:
        raise ArtifactError(f"{stage_dir}/manifest.json: no 'target' input recorded")
    return Path(records[0]["path"])


def same_boxes(rc_boxes: np.ndarray, cf_boxes: np.ndarray) -> bool:
    """Whether RC's and CF's output boxes `(N, 7)` are one box table: the same rows, centres and
    sizes, headings equal up to a half turn (--orient-models turns a box round in one stage and
    not the other: RC only turns the boxes it re-casts)."""
    if rc_boxes.shape != cf_boxes.shape or not np.array_equal(rc_boxes[:, :6], cf_boxes[:, :6]):
        return False
    return bool(np.allclose(wrap_angle(2 * (rc_boxes[:, 6] - cf_boxes[:, 6])), 0.0, atol=1e-9))


def pick_examples(rc_table, cf_table, count: int) -> np.ndarray:
    """Rows `(<= count,)` replaced by both RC and CF, spread over the range of raw point counts."""
    both = np.flatnonzero(
        (np.asarray(rc_table["ppcg"]) == "rc") & (np.asarray(cf_table["ppcg"]) == "cf")
    )
    if len(both) == 0:
        return both
    order = both[np.argsort(rc_table["points_before"][both], kind="stable")]
    return order[
        np.unique(np.linspace(0, len(order) - 1, min(count, len(order))).round().astype(int))
    ]


def _local(points: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Points `(n, >=3)` -> box-frame metres `(m, 3)` of those within the box plus a margin."""
    local = sensor_to_model(points[:, :3].astype(np.float64), box) * box[3:6]
    inside = (np.abs(local) <= box[3:6] / 2 + _MARGIN_M).all(axis=1)
    return local[inside]


def plot_ppcg_examples(
    rc_dir: str | Path, cf_dir: str | Path, out_png: str | Path, count: int = 4
) -> Path | None:
    """Draw up to `count` boxes (rows) x {raw, RC, CF} x {BEV, side}; None when no box qualifies."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rc_dir, cf_dir = Path(rc_dir), Path(cf_dir)
    rc_table, cf_table = read_boxes(rc_dir), read_boxes(cf_dir)
    if not same_boxes(rc_table.boxes, cf_table.boxes):
        raise ArtifactError(f"{rc_dir} and {cf_dir}: not made from the same box table")
    rows = pick_examples(rc_table, cf_table, count)
    if len(rows) == 0:
        return None
    frame_sets = {
        "raw": FrameSet(_target_of(rc_dir)),
        "RC": FrameSet(rc_dir),
        "CF": FrameSet(cf_dir),
    }
    figure, axes = plt.subplots(2 * len(rows), 3, figsize=(9.0, 3.2 * len(rows)), squeeze=False)
    for position, row in enumerate(rows):
        box = rc_table.boxes[row]
        frame_id = str(rc_table.frame_id[row])
        half = box[3:6] / 2
        for column, (name, frames) in enumerate(frame_sets.items()):
            local = _local(frames.frame(frame_id), box)
            for view, (a, b, label) in enumerate(((0, 1, "y"), (0, 2, "z"))):
                axis = axes[2 * position + view, column]
                axis.scatter(local[:, a], local[:, b], s=2, c="tab:blue", linewidths=0)
                axis.add_patch(
                    plt.Rectangle(
                        (-half[a], -half[b]), 2 * half[a], 2 * half[b], fill=False, ec="tab:red"
                    )
                )
                axis.set_xlim(-half[a] - _MARGIN_M, half[a] + _MARGIN_M)
                axis.set_ylim(-half[b] - _MARGIN_M, half[b] + _MARGIN_M)
                axis.set_aspect("equal")
                axis.tick_params(labelsize=6)
                axis.set_xlabel("x along heading (m)", fontsize=6)
                axis.set_ylabel(f"{label} (m)", fontsize=6)
                if view == 0:
                    range_m = float(np.hypot(box[0], box[1]))
                    axis.set_title(
                        f"{name}: frame {frame_id}, {range_m:.0f} m, {len(local)} pts", fontsize=7
                    )
    figure.suptitle(
        "PPCG: raw / RC / CF points per box (top: bird's-eye, bottom: side)", fontsize=9
    )
    figure.tight_layout()
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out_png, dpi=110)
    plt.close(figure)
    return out_png
