"""How alike two LiDAR domains look: per-frame-set statistics of points (count in view, intensity,
height, range) and of labelled cars (per frame, beyond 40 m, points per car by range band, how far
their surface sits inside their boxes), over the points in a camera-like view in front of the
sensor. Pure functions over arrays."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dali_cli.geometry import count_points_in_boxes
from dali_cli.reporting.surface_inset import surface_insets

CAR_BANDS_M = ((10.0, 20.0), (20.0, 30.0), (30.0, 40.0), (40.0, 60.0))
FAR_CAR_M = 40.0
# sample of per-point values kept per frame for the distribution plots (all frames together stay
# small; the statistics themselves use every point)
SAMPLE_PER_FRAME = 4000


def in_view(xy: np.ndarray, view_deg: float | None) -> np.ndarray:
    """`(N,)` bool: positions `(N, 2+)` (sensor frame, x forward) within +-view_deg/2 of +x.

    view_deg None or >= 360 keeps everything (the full circle).
    """
    xy = np.asarray(xy)
    if view_deg is None or view_deg >= 360.0:
        return np.ones(len(xy), bool)
    azimuth = np.arctan2(xy[:, 1], xy[:, 0])
    return np.abs(azimuth) <= np.radians(view_deg) / 2


@dataclass
class FrameStats:
    """One frame's raw material: per point in view intensity, z, range `(n,)`; per car in view
    (>= 1 point) its range `(k,)`, points `(k,)` and end- and side-face insets `(k, 2)` (m, NaN
    where not measured; `surface_inset.surface_insets`)."""

    points: int
    intensity: np.ndarray
    height: np.ndarray
    range_m: np.ndarray
    car_range_m: np.ndarray
    car_points: np.ndarray
    car_insets: np.ndarray


def frame_stats(
    points: np.ndarray, boxes: np.ndarray, view_deg: float | None, rng: np.random.Generator
) -> FrameStats:
    """Statistics material of one frame: points `(N, 4)` x, y, z, intensity (sensor frame, m) and
    car boxes `(K, 7)`; only points and car centers in the view count, and a car counts when at
    least one point in view lies in its box. Per-point arrays are a sample of at most
    SAMPLE_PER_FRAME points (`rng` draws it); `points` is the full count."""
    points = np.asarray(points, np.float32).reshape(-1, 4)
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    kept = points[in_view(points, view_deg)]
    count = len(kept)
    if count > SAMPLE_PER_FRAME:
        kept_sample = kept[rng.choice(count, SAMPLE_PER_FRAME, replace=False)]
    else:
        kept_sample = kept
    cars = boxes[in_view(boxes, view_deg)]
    per_car = count_points_in_boxes(kept[:, :3], cars) if len(cars) else np.zeros(0, np.int32)
    seen = per_car >= 1
    return FrameStats(
        points=count,
        intensity=kept_sample[:, 3].astype(np.float64),
        height=kept_sample[:, 2].astype(np.float64),
        range_m=np.hypot(kept_sample[:, 0], kept_sample[:, 1]).astype(np.float64),
        car_range_m=np.hypot(cars[seen, 0], cars[seen, 1]),
        car_points=per_car[seen].astype(np.int64),
        car_insets=surface_insets(kept, cars[seen]),
    )


@dataclass
class DomainStats:
    """A frame set's statistics (see `summarize`) and the samples they came from."""

    frames: int
    values: dict
    samples: dict = field(repr=False)


def _weighted_quantiles(values: np.ndarray, weights: np.ndarray, q: list[float]) -> list[float]:
    """Quantiles `q` of `values` where each value stands for `weights` of them (per-frame samples
    of different sizes stand for their frames' full point counts)."""
    if len(values) == 0:
        return [float("nan")] * len(q)
    order = np.argsort(values, kind="stable")
    cumulative = np.cumsum(weights[order])
    positions = (np.asarray(q) * cumulative[-1]).clip(0, cumulative[-1])
    index = np.searchsorted(cumulative, positions, side="left").clip(0, len(values) - 1)
    return [float(v) for v in values[order][index]]


def summarize(frames: list[FrameStats]) -> DomainStats:
    """The statistics of a frame set from its frames' material.

    points_per_frame: mean points in view; intensity mean / median / p90, median height (sensor z,
    m), median range (m, in the ground plane): over all points in view, each frame's sample
    weighted by its full count; cars_per_frame: mean cars in view with >= 1 point;
    cars_beyond_40m / cars: how many of them lie beyond 40 m; points_per_car_<band>: median
    points of the cars in each range band (None when the band holds no car), with their count;
    end_face_inset_m / side_face_inset_m: median depth of the car surface inside its box's end
    and side faces (None when no car's face was measured), with the count of cars measured.
    """
    counts = np.array([f.points for f in frames], np.float64)
    values = np.concatenate([f.intensity for f in frames]) if frames else np.zeros(0)
    heights = np.concatenate([f.height for f in frames]) if frames else np.zeros(0)
    ranges = np.concatenate([f.range_m for f in frames]) if frames else np.zeros(0)
    weights = np.concatenate(
        [np.full(len(f.intensity), f.points / max(len(f.intensity), 1)) for f in frames]
        if frames
        else [np.zeros(0)]
    )
    car_range = np.concatenate([f.car_range_m for f in frames]) if frames else np.zeros(0)
    car_points = np.concatenate([f.car_points for f in frames]) if frames else np.zeros(0)
    car_insets = (
        np.concatenate([f.car_insets for f in frames]) if frames else np.zeros((0, 2))
    ).reshape(-1, 2)
    mean_intensity = (
        float(np.average(values, weights=weights)) if weights.sum() > 0 else float("nan")
    )
    median_i, p90_i = _weighted_quantiles(values, weights, [0.5, 0.9])
    stats = {
        "frames": len(frames),
        "points_per_frame": float(counts.mean()) if len(counts) else float("nan"),
        "intensity_mean": mean_intensity,
        "intensity_median": median_i,
        "intensity_p90": p90_i,
        "height_median_m": _weighted_quantiles(heights, weights, [0.5])[0],
        "range_median_m": _weighted_quantiles(ranges, weights, [0.5])[0],
        "cars": int(len(car_range)),
        "cars_per_frame": len(car_range) / len(frames) if frames else float("nan"),
        "cars_beyond_40m": int((car_range > FAR_CAR_M).sum()),
    }
    for low, high in CAR_BANDS_M:
        band = (car_range >= low) & (car_range < high)
        key = f"points_per_car_{low:.0f}_{high:.0f}m"
        stats[key] = float(np.median(car_points[band])) if band.any() else None
        stats[f"cars_{low:.0f}_{high:.0f}m"] = int(band.sum())
    for column, face in enumerate(("end", "side")):
        measured = car_insets[:, column][np.isfinite(car_insets[:, column])]
        stats[f"{face}_face_inset_m"] = float(np.median(measured)) if measured.size else None
        stats[f"cars_{face}_face"] = int(measured.size)
    samples = {
        "intensity": values,
        "height": heights,
        "range": ranges,
        "weights": weights,
        "points_per_frame": counts,
        "car_range": car_range,
        "car_points": car_points,
    }
    return DomainStats(frames=len(frames), values=stats, samples=samples)


# rows of the printed table: (label, key or keys, format)
TABLE_ROWS = (
    ("frames", ("frames",), "{:.0f}"),
    ("points per frame in view", ("points_per_frame",), "{:,.0f}"),
    ("intensity mean / median / p90", ("intensity_mean", "intensity_median", "intensity_p90"),
     "{:.2f}"),
    ("median point height (sensor z, m)", ("height_median_m",), "{:.2f}"),
    ("median point range (m)", ("range_median_m",), "{:.1f}"),
    ("cars per frame in view", ("cars_per_frame",), "{:.1f}"),
    ("cars beyond 40 m / cars", ("cars_beyond_40m", "cars"), "{:.0f}"),
    *(
        (f"points per car {low:.0f}-{high:.0f} m (median, n)",
         (f"points_per_car_{low:.0f}_{high:.0f}m", f"cars_{low:.0f}_{high:.0f}m"), "{:.0f}")
        for low, high in CAR_BANDS_M
    ),
    ("car surface inside its box, end face (median m, n)", ("end_face_inset_m", "cars_end_face"),
     "{:.3f}"),
    ("car surface inside its box, side face (median m, n)",
     ("side_face_inset_m", "cars_side_face"), "{:.3f}"),
)  # fmt: skip


def _cell(values: dict, keys: tuple[str, ...], form: str) -> str:
    parts = []
    for key in keys:
        value = values.get(key)
        if value is None or (isinstance(value, float) and np.isnan(value)):
            parts.append("-")
        elif isinstance(value, (int, np.integer)):
            parts.append(str(value))  # counts stay whole whatever the row's format
        else:
            parts.append(form.format(value))
    return " / ".join(parts)


def format_table(named: list[tuple[str, dict]]) -> str:
    """A plain-text table: one row per statistic, one column per frame set `(name, values)`."""
    header = ["statistic", *[name for name, _ in named]]
    rows = [header] + [
        [label, *[_cell(values, keys, form) for _, values in named]]
        for label, keys, form in TABLE_ROWS
    ]
    widths = [max(len(row[c]) for row in rows) for c in range(len(header))]
    lines = [
        "  ".join(cell.ljust(widths[c]) if c == 0 else cell.rjust(widths[c]) for c, cell in
                  enumerate(row))
        for row in rows
    ]  # fmt: skip
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Plots

_HISTOGRAMS = (
    ("intensity", "intensity", np.linspace(0.0, 1.0, 51)),
    ("height", "point height, sensor z (m)", np.linspace(-3.0, 5.0, 81)),
    ("range", "point range in the ground plane (m)", np.linspace(0.0, 80.0, 81)),
)


def plot_domains(named: list[tuple[str, DomainStats]], out_dir, dpi: int = 110) -> list:
    """PNGs of the domains' distributions into `out_dir`: point intensity, height and range
    (densities, each frame's sample weighted by its count), cars by range, and points per car
    against range (log scale). Returns the written paths."""
    from pathlib import Path

    from dali_cli.reporting.plots import _pyplot, _save

    plt = _pyplot()
    out_dir = Path(out_dir)
    written = []
    for key, xlabel, bins in _HISTOGRAMS:
        figure, axes = plt.subplots(figsize=(6, 4))
        for name, stats in named:
            values, weights = stats.samples[key], stats.samples["weights"]
            if len(values):
                axes.hist(values, bins=bins, weights=weights, density=True, histtype="step",
                          label=name)  # fmt: skip
        axes.set_xlabel(xlabel)
        axes.set_ylabel("density")
        axes.legend()
        written.append(_save(plt, figure, out_dir / f"{key}.png", dpi))
    figure, axes = plt.subplots(figsize=(6, 4))
    for name, stats in named:
        if stats.frames:
            ranges = stats.samples["car_range"]
            weights = np.full(len(ranges), 1.0 / stats.frames)
            axes.hist(ranges, bins=np.arange(0.0, 85.0, 5.0), weights=weights, histtype="step",
                      label=name)  # fmt: skip
    axes.set_xlabel("car range (m)")
    axes.set_ylabel("cars per frame")
    axes.legend()
    written.append(_save(plt, figure, out_dir / "car_range.png", dpi))
    figure, axes = plt.subplots(figsize=(6, 4))
    for name, stats in named:
        axes.scatter(stats.samples["car_range"], np.maximum(stats.samples["car_points"], 1), s=6,
                     alpha=0.5, label=name)  # fmt: skip
    axes.set_yscale("log")
    axes.set_xlabel("car range (m)")
    axes.set_ylabel("points per car")
    axes.legend()
    written.append(_save(plt, figure, out_dir / "points_per_car.png", dpi))
    return written
