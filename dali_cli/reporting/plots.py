"""Plots of a run for `dali report`: PTSN curves, pseudo-label and predicted size distributions,
bird's-eye views of predictions, the error breakdown and PPCG examples.

Each plot is drawn only from artifacts the run holds; a missing artifact means a missing plot.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dali_cli.labels import SCORE_MIN
from dali_cli.store.regular_files import read_json_file
from dali_cli.store.scale_file import read_scale


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt, figure, out: Path, dpi: int) -> Path:
    """Lay out, write the PNG (creating its directory) and free the figure."""
    figure.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out, dpi=dpi)
    plt.close(figure)
    return out


def _volume_column(names: list[str]) -> str | None:
    for candidate in ("mean_volume", "mean_volume_m3", "volume"):
        if candidate in names:
            return candidate
    return next((name for name in names if "volume" in name), None)


def plot_ptsn_curves(run: Path, out: Path) -> Path | None:
    """Mean predicted volume vs scale for every iteration's sweep, E_est line and ŝ marked."""
    import pyarrow.parquet as pq

    sweeps = sorted(run.glob("iter*/ptsn/sweep.parquet"))
    if not sweeps:
        return None
    plt = _pyplot()
    figure, axis = plt.subplots(figsize=(6, 4))
    expected_volume = None
    for path in sweeps:
        table = pq.read_table(path).to_pydict()
        column = _volume_column(list(table))
        if column is None or "scale" not in table:
            continue
        subset = np.asarray(table.get("subset", ["all"] * len(table["scale"])))
        scales_all = np.asarray(table["scale"], float)
        volumes_all = np.asarray(table[column], float)
        label = path.parent.parent.name
        # the bracket search evaluates a frame subsample first, then confirms on all frames:
        # the two are different curves, so only "all" is joined by a line
        whole = subset == "all"
        order = np.argsort(scales_all[whole])
        (line,) = axis.plot(
            scales_all[whole][order],
            volumes_all[whole][order],
            "o-",
            ms=3,
            label=f"{label} E_pred(s)",
        )
        if (~whole).any():
            axis.plot(
                scales_all[~whole],
                volumes_all[~whole],
                "o",
                ms=4,
                mfc="none",
                color=line.get_color(),
                alpha=0.6,
                label=f"{label} (frame subsample)",
            )
        info_path = path.parent / "scale.json"
        if info_path.is_file():
            info = read_scale(info_path).record
            axis.axvline(info["scale"], color=line.get_color(), ls=":", lw=1)
            estimate = info.get("expected_volume") or info.get("E_est_volume")
            if estimate is None and isinstance(info.get("expected_lwh"), list):
                estimate = float(np.prod(info["expected_lwh"]))
            expected_volume = estimate if estimate is not None else expected_volume
    if expected_volume is not None:
        axis.axhline(expected_volume, color="k", ls="--", lw=1, label="E_est")
    axis.set_xlabel("scale s")
    axis.set_ylabel("mean predicted car volume (m³)")
    axis.set_title("PTSN sweep")
    axis.legend(fontsize=8)
    return _save(plt, figure, out, dpi=120)


def plot_size_distributions(run: Path, out: Path, target: Path | None = None) -> Path | None:
    """Histograms of pseudo-label l, w, h per iteration against the target's label sizes."""
    from dali_cli.store.artifacts import read_boxes

    pseudo_dirs = sorted(p.parent for p in run.glob("iter*/pseudo/boxes.parquet"))
    if not pseudo_dirs:
        return None
    target = target or run / "data" / "target"
    plt = _pyplot()
    figure, axes = plt.subplots(1, 3, figsize=(11, 3.4))
    truth = read_boxes(target) if (target / "boxes.parquet").is_file() else None
    for index, name in enumerate(("length l (m)", "width w (m)", "height h (m)")):
        axis = axes[index]
        if truth is not None and len(truth):
            cars = truth.select(truth["label"] == "Car")
            axis.hist(
                cars.boxes[:, 3 + index],
                bins=30,
                density=True,
                alpha=0.35,
                color="k",
                label="ground truth",
            )
        for directory in pseudo_dirs:
            boxes = read_boxes(directory).boxes
            if len(boxes):
                axis.hist(
                    boxes[:, 3 + index],
                    bins=30,
                    density=True,
                    histtype="step",
                    lw=1.5,
                    label=f"pseudo {directory.parent.name}",
                )
        axis.set_xlabel(name)
    axes[0].legend(fontsize=8)
    figure.suptitle("Pseudo-label sizes vs target ground truth")
    return _save(plt, figure, out, dpi=120)


# rows of the results table whose evaluation predictions are compared (paper Fig. 1a)
SIZE_ROWS = (
    ("Source only", "iter0/eval"),
    ("SN", "baselines/sn/eval"),
    ("PTSN only", "iter0/eval_ptsn"),
    ("DALI x1", "iter1/eval"),
    ("DALI x2", "iter2/eval"),
)


def _evaluation(run: Path, relative: str):
    """(predictions BoxTable, metrics dict) of an evaluation directory, or None."""
    from dali_cli.store.artifacts import read_boxes

    directory = run / relative
    if (
        not (directory / "predictions.parquet").is_file()
        or not (directory / "metrics.json").is_file()
    ):
        return None
    metrics = read_json_file(directory / "metrics.json", "metrics file")
    return read_boxes(directory / "predictions.parquet"), metrics


def _ground_truth(run: Path, metrics: dict):
    """The evaluated frame set's directory and labels (the path recorded in metrics.json)."""
    from dali_cli.store.artifacts import read_boxes

    recorded = metrics.get("Car", {}).get("source", {}).get("data")
    candidates = [Path(recorded)] if recorded else []
    candidates += [run / "data" / "target_val"]
    for directory in candidates:
        if (directory / "boxes.parquet").is_file():
            truth = read_boxes(directory)
            return directory, truth.select(np.asarray(truth["label"]) == "Car")
    return None, None


def evaluations(run: Path) -> list[tuple[str, tuple]]:
    """(row name, (predictions, metrics)) of every SIZE_ROWS evaluation the run holds."""
    found = [(name, _evaluation(run, relative)) for name, relative in SIZE_ROWS]
    return [(name, result) for name, result in found if result is not None]


def plot_method_sizes(run: Path, out: Path, found: list | None = None) -> Path | None:
    """Predicted l, w, h (score >= 0.3) of each method row against the target ground truth."""
    found = evaluations(run) if found is None else found
    if not found:
        return None
    _, truth = _ground_truth(run, found[0][1][1])
    plt = _pyplot()
    figure, axes = plt.subplots(1, 3, figsize=(11, 3.4))
    for index, name in enumerate(("length l (m)", "width w (m)", "height h (m)")):
        axis = axes[index]
        edges = np.linspace((1.0, 1.0, 0.8)[index], (6.5, 3.0, 2.4)[index], 45)
        if truth is not None and len(truth):
            values = truth.boxes[:, 3 + index]
            axis.hist(values, bins=edges, density=True, alpha=0.3, color="k", label="ground truth")
        for row, (pred, _) in found:
            keep = np.asarray(pred["score"]) >= SCORE_MIN
            if keep.any():
                values = pred.boxes[keep, 3 + index]
                axis.hist(values, bins=edges, density=True, histtype="step", lw=1.4, label=row)
        axis.set_xlabel(name)
    axes[0].legend(fontsize=7)
    figure.suptitle(f"Predicted car sizes on the target (score >= {SCORE_MIN}) vs ground truth")
    return _save(plt, figure, out, dpi=120)


def plot_bev_views(run: Path, out: Path, frames: int = 2, found: list | None = None) -> Path | None:
    """Bird's-eye views of target validation frames: points, ground truth and the predictions
    (score >= 0.3) of the first and the last method row that was evaluated."""
    from dali_cli.geometry import bev_corners
    from dali_cli.store.artifacts import FrameSet

    found = evaluations(run) if found is None else found
    if not found:
        return None
    shown = [found[0]] if len(found) == 1 else [found[0], found[-1]]
    data_dir, truth = _ground_truth(run, found[0][1][1])
    if data_dir is None:
        return None
    frame_set = FrameSet(data_dir)
    frame_ids = list(frame_set.frame_ids)[:frames]
    plt = _pyplot()
    figure, axes = plt.subplots(
        len(frame_ids), len(shown), figsize=(5.5 * len(shown), 4.2 * len(frame_ids)), squeeze=False
    )
    for row_index, frame_id in enumerate(frame_ids):
        points = frame_set.frame(frame_id)
        ahead = (points[:, 0] > -5) & (points[:, 0] < 72) & (np.abs(points[:, 1]) < 42)
        gt_boxes = truth.boxes[np.asarray(truth.frame_id) == frame_id] if truth is not None else []
        for column, (name, (pred, _)) in enumerate(shown):
            axis = axes[row_index, column]
            axis.scatter(points[ahead, 0], points[ahead, 1], s=0.05, c="0.55", linewidths=0)
            for corners in bev_corners(gt_boxes) if len(gt_boxes) else []:
                axis.fill(corners[:, 0], corners[:, 1], fill=False, ec="g", lw=1.2)
            mine = (np.asarray(pred.frame_id) == frame_id) & (
                np.asarray(pred["score"]) >= SCORE_MIN
            )
            for corners in bev_corners(pred.boxes[mine]) if mine.any() else []:
                axis.fill(corners[:, 0], corners[:, 1], fill=False, ec="r", lw=0.9)
            axis.set_title(f"{name}: frame {frame_id} (green: truth, red: predicted)", fontsize=9)
            axis.set_xlim(-5, 72)
            axis.set_ylim(-42, 42)
            axis.set_aspect("equal")
            axis.set_xlabel("x (m)")
            axis.set_ylabel("y (m)")
    return _save(plt, figure, out, dpi=110)


def plot_ppcg(run: Path, out_dir: Path) -> list[Path]:
    """Raw / RC / CF views of a few pseudo boxes (paper Fig. 9) for every iteration with both."""
    from dali_cli.ppcg.figure import plot_ppcg_examples

    drawn = []
    for rc_dir in sorted(run.glob("iter*/rc")):
        cf_dir = rc_dir.parent / "cf"
        if (rc_dir / "manifest.json").is_file() and (cf_dir / "manifest.json").is_file():
            path = plot_ppcg_examples(rc_dir, cf_dir, out_dir / f"ppcg_{rc_dir.parent.name}.png")
            if path is not None:
                drawn.append(Path(path))
    return drawn


def plot_error_breakdown(run: Path, out: Path) -> Path | None:
    """Per method row with an error breakdown in its metrics.json: the median box error of the
    matches and its 16-84 % interval per range band (one panel per quantity), and the AP_3D at
    IoU 0.7 each fix would gain (last panel)."""
    from dali_cli.evaluation.errors import ERROR_BANDS_M, FIXES, QUANTITIES
    from dali_cli.reporting.report import BREAKDOWN_IOU, CONTROL_ROWS, ROWS, collect_rows

    rows = [row for row in collect_rows(run, ROWS + CONTROL_ROWS) if row.errors]
    if not rows:
        return None
    plt = _pyplot()
    figure, axes = plt.subplots(2, 4, figsize=(14, 6.4))
    bands = list(ERROR_BANDS_M)
    width = 0.8 / len(rows)
    for index, row in enumerate(rows):
        shift = (index - (len(rows) - 1) / 2) * width
        matches = row.errors["true_positives"]
        for axis, quantity in zip(axes.flat, QUANTITIES, strict=False):
            stats = [matches[band].get(quantity, {}) for band in bands]
            at = [k for k, entry in enumerate(stats) if entry.get("median") is not None]
            median = np.array([stats[k]["median"] for k in at])
            spread = np.array([[median[j] - stats[k]["p16"], stats[k]["p84"] - median[j]]
                               for j, k in enumerate(at)]).reshape(-1, 2).T  # fmt: skip
            axis.errorbar(np.asarray(at) + shift, median, yerr=spread, fmt="o", ms=4, capsize=2,
                          label=row.name)  # fmt: skip
        block = row.errors["false_positives"].get(BREAKDOWN_IOU, {}).get("3d", {})
        base = block.get("ap")
        gains = [
            (block["ap_fixed"][name] - base) if base is not None and block["ap_fixed"][name]
            is not None else 0.0 for name in FIXES
        ]  # fmt: skip
        axes.flat[-1].bar(np.arange(len(FIXES)) + shift, gains, width, label=row.name)
    for axis, quantity in zip(axes.flat, QUANTITIES, strict=False):
        axis.axhline(0, color="0.6", lw=0.8)
        axis.set_xticks(
            range(len(bands)),
            [band if band == "all" else f"{band} m" for band in bands],
            fontsize=8,
        )
        axis.set_title(f"{quantity} (pred − truth)", fontsize=9)
    last = axes.flat[-1]
    last.set_xticks(range(len(FIXES)), list(FIXES), fontsize=8)
    last.set_title(f"AP_3D@{BREAKDOWN_IOU} gained if fixed", fontsize=9)
    axes.flat[0].legend(fontsize=7)
    matches = rows[0].errors["true_positives"]
    figure.suptitle(
        f"Box errors of the matches ({matches['overlap'].upper()} IoU > {matches['iou']:g}): "
        "median and 16-84 % per range band; false positives' cost"
    )
    return _save(plt, figure, out, dpi=110)


def draw_plots(run: Path, out_dir: Path) -> list[Path]:
    """Every plot the run's artifacts allow; [] (and no error) when matplotlib is missing."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return []
    found = evaluations(run)  # predictions are read once for both plots that use them
    drawn = [
        plot_ptsn_curves(run, out_dir / "ptsn_curves.png"),
        plot_size_distributions(run, out_dir / "pseudo_sizes.png"),
        plot_method_sizes(run, out_dir / "method_sizes.png", found),
        plot_bev_views(run, out_dir / "bev_views.png", found=found),
        plot_error_breakdown(run, out_dir / "error_breakdown.png"),
        *plot_ppcg(run, out_dir),
    ]
    return [path for path in drawn if path is not None]


def plot_sweep(rows: Sequence[dict], scale: float, e_est, path, title: str = "") -> None:
    """Mean predicted volume vs scale with the E_est volume line and ŝ marked (paper Fig. 3)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    for subset, marker, colour in (("all", "o-", "tab:blue"), ("subsample", "x", "tab:gray")):
        points = sorted(
            (r["scale"], r["mean_volume"])
            for r in rows
            if r["subset"] == subset and math.isfinite(r["mean_volume"])
        )
        if points:
            xs, ys = zip(*points, strict=True)
            label = "E_pred, all frames" if subset == "all" else "E_pred, subsample"
            axis.plot(xs, ys, marker, color=colour, markersize=4, label=label)
    target_volume = float(np.prod(e_est))
    axis.axhline(
        target_volume, color="tab:red", linestyle="--", label=f"E_est {target_volume:.2f} m³"
    )
    axis.axvline(scale, color="tab:green", linestyle=":", label=f"ŝ = {scale:.3f}")
    axis.set_xlabel("scale s")
    axis.set_ylabel("mean predicted volume (m³)")
    axis.set_title(title or "PTSN sweep")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)
