"""Pictures of one frame for checking data by eye: a bird's-eye view of the points with the boxes of
several sources in different colours, and optionally a side view (x-z) below it. Matplotlib, Agg.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dali_cli.geometry import bev_corners, box_corners

# Box colours by source, in order (colour-blind safe Okabe-Ito), then matplotlib's tab10.
BOX_COLOURS = ("#E69F00", "#56B4E9", "#009E73", "#D55E00", "#CC79A7", "#0072B2", "#F0E442")


@dataclass
class BoxSet:
    """Boxes of one source for one frame: name, boxes (N, 7), labels (N,) str, scores (N,) or None."""

    name: str
    boxes: np.ndarray
    labels: np.ndarray
    scores: np.ndarray | None = None


def auto_extent(points: np.ndarray, box_sets: list[BoxSet], quantile: float = 0.995) -> tuple:
    """BEV limits (xmin, xmax, ymin, ymax) in metres: the central `quantile` of the points' x and
    y, widened to include the sensor and every box, with a 2 m margin."""
    if len(points):
        lo = np.minimum(np.quantile(points[:, :2], 1 - quantile, axis=0), 0.0)
        hi = np.maximum(np.quantile(points[:, :2], quantile, axis=0), 0.0)
    else:
        lo, hi = np.full(2, -10.0), np.full(2, 10.0)
    for box_set in box_sets:
        if len(box_set.boxes):
            corners = bev_corners(box_set.boxes).reshape(-1, 2)
            lo = np.minimum(lo, corners.min(axis=0))
            hi = np.maximum(hi, corners.max(axis=0))
    return float(lo[0] - 2), float(hi[0] + 2), float(lo[1] - 2), float(hi[1] + 2)


def render_frame(
    points: np.ndarray,
    box_sets: list[BoxSet],
    out_path: str | Path,
    title: str = "",
    side: bool = False,
    extent: tuple[float, float, float, float] | None = None,
    colour_by: str = "z",
    width_px: int = 1200,
    annotate: bool = False,
) -> Path:
    """Draw `(n, >=4)` points and the box sets into a PNG at `out_path` (written atomically).

    BEV: x to the right, y up (so yaw is counter-clockwise on the page), points coloured by
    height ('z') or intensity ('intensity'); each box is its rectangle plus a line from the centre
    to the front. Boxes whose label is not Car are dashed; zero-size boxes (DontCare) are skipped.
    Side view (x horizontal, z up): every box's x-z extent. Returns the path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = np.asarray(points, np.float64)
    xmin, xmax, ymin, ymax = extent or auto_extent(points, box_sets)
    inside = (
        (points[:, 0] >= xmin)
        & (points[:, 0] <= xmax)
        & (points[:, 1] >= ymin)
        & (points[:, 1] <= ymax)
    )
    shown = points[inside]
    values = shown[:, 2] if colour_by == "z" else shown[:, 3]
    limits = np.quantile(values, [0.01, 0.99]) if len(values) else (0.0, 1.0)
    dpi = 100
    figure, axes = frame_figure((xmax - xmin, ymax - ymin), side, width_px, dpi)
    bev = axes[0, 0]
    bev.set_facecolor("black")
    bev.scatter(
        shown[:, 0], shown[:, 1], c=values, s=0.6, cmap="viridis", vmin=limits[0], vmax=limits[1],
        linewidths=0, rasterized=True,
    )  # fmt: skip
    bev.plot([0], [0], marker=">", color="white", markersize=8)  # the sensor, facing +x
    handles = [
        draw_bev_boxes(bev, box_set, BOX_COLOURS[index % len(BOX_COLOURS)], annotate)
        for index, box_set in enumerate(box_sets)
    ]
    bev.set_xlim(xmin, xmax)
    bev.set_ylim(ymin, ymax)
    bev.set_aspect("equal")
    bev.set_ylabel("y (m)")
    if handles:
        bev.legend(
            handles=handles, loc="upper right", fontsize=8, facecolor="white", framealpha=0.8
        )
    bev.set_title(title, fontsize=10)
    if side:
        draw_side_view(axes[1, 0], shown, values, limits, box_sets)
    axes[-1, 0].set_xlabel("x (m)")
    figure.tight_layout()
    from dali_cli.store.atomic_file import write_atomically
    from dali_cli.store.output_paths import PNG_SOFTWARE

    try:
        write_atomically(
            out_path,
            lambda temporary: figure.savefig(
                temporary, dpi=dpi, format="png", metadata={"Software": PNG_SOFTWARE}
            ),
        )
    finally:
        plt.close(figure)
    return out_path


def frame_figure(bev_size_m: tuple[float, float], side: bool, width_px: int, dpi: int):
    """(figure, axes (rows, 1)): the BEV axes sized to the x, y extent in metres `bev_size_m`,
    and a side view a quarter of the width high under it."""
    import matplotlib.pyplot as plt

    bev_height = bev_size_m[1] / bev_size_m[0]
    heights = [bev_height, 0.25] if side else [bev_height]
    width_in = width_px / dpi
    return plt.subplots(
        len(heights),
        1,
        figsize=(width_in, width_in * sum(heights) + 0.6),
        dpi=dpi,
        gridspec_kw={"height_ratios": heights},
        squeeze=False,
        sharex=True,
    )


def draw_bev_boxes(bev, box_set: BoxSet, colour: str, annotate: bool):
    """One source's boxes on the BEV axes (rectangle + centre-to-front line; non-Car dashed;
    zero-size boxes skipped), with their scores or labels when `annotate`; returns its legend
    handle."""
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection, PolyCollection

    boxes = np.asarray(box_set.boxes, np.float64).reshape(-1, 7)
    drawn = (boxes[:, 3:6] > 0).all(axis=1)
    boxes, labels = boxes[drawn], np.asarray(box_set.labels).astype(str)[drawn]
    styles = np.where(labels == "Car", "solid", "dashed")
    corners = bev_corners(boxes) if len(boxes) else np.zeros((0, 4, 2))  # (N, 4, 2)
    bev.add_collection(
        PolyCollection(
            corners, closed=True, facecolors="none", edgecolors=colour, linewidths=1.2,
            linestyles=list(styles),
        )
    )  # fmt: skip
    front = (corners[:, 0] + corners[:, 3]) / 2  # (N, 2) midpoint of the front edge
    bev.add_collection(
        LineCollection(np.stack([boxes[:, :2], front], axis=1), colors=colour, linewidths=1.2)
    )
    if annotate:
        scores = None if box_set.scores is None else np.asarray(box_set.scores)[drawn]
        for i in range(len(boxes)):
            text = labels[i] if scores is None else f"{scores[i]:.2f}"
            bev.text(
                boxes[i, 0], boxes[i, 1], text, color=colour, fontsize=7, ha="center", va="center"
            )
    return plt.Line2D([], [], color=colour, label=f"{box_set.name} ({int(drawn.sum())})")


def draw_side_view(axis, shown: np.ndarray, values: np.ndarray, limits, box_sets: list) -> None:
    """The side view (x horizontal, z up): the shown points `(n, >=3)` coloured by `values`
    and every box's x-z extent."""
    from matplotlib.collections import PolyCollection

    axis.set_facecolor("black")
    axis.scatter(shown[:, 0], shown[:, 2], c=values, s=0.4, cmap="viridis", vmin=limits[0], vmax=limits[1],
                 linewidths=0, rasterized=True)  # fmt: skip
    for index, box_set in enumerate(box_sets):
        colour = BOX_COLOURS[index % len(BOX_COLOURS)]
        boxes = np.asarray(box_set.boxes, np.float64).reshape(-1, 7)
        boxes = boxes[(boxes[:, 3:6] > 0).all(axis=1)]
        if len(boxes):
            corners = box_corners(boxes)  # (N, 8, 3)
            x0, x1 = corners[:, :, 0].min(axis=1), corners[:, :, 0].max(axis=1)
            z0, z1 = corners[:, :, 2].min(axis=1), corners[:, :, 2].max(axis=1)
            rectangles = np.stack(
                [np.c_[x0, z0], np.c_[x1, z0], np.c_[x1, z1], np.c_[x0, z1]], axis=1
            )
            axis.add_collection(
                PolyCollection(rectangles, facecolors="none", edgecolors=colour, linewidths=1)
            )
    z = shown[:, 2] if len(shown) else np.zeros(1)
    axis.set_ylim(float(np.quantile(z, 0.005)) - 0.5, float(np.quantile(z, 0.995)) + 0.5)
    axis.set_ylabel("z (m)")
