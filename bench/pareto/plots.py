"""One PNG per front: measured (cost, error) points, the non-dominated ones joined, defaults marked."""

from __future__ import annotations

from pathlib import Path


def non_dominated(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats on both cost and error (lower is better)."""
    keep = []
    for i, (cost, error) in enumerate(points):
        beaten = any(
            (c <= cost and e <= error) and (c < cost or e < error)
            for j, (c, e) in enumerate(points)
            if j != i
        )
        if not beaten:
            keep.append(i)
    return sorted(keep, key=lambda i: points[i][0])


def front_plot(
    path: Path,
    title: str,
    points: list[dict],
    cost: str,
    error: str,
    label,
    xlabel: str,
    ylabel: str,
    note: str = "",
    logx: bool = False,
    logy: bool = False,
) -> list[int]:
    """Scatter `points` (dicts with `cost`, `error`, `default`); returns the front's indices."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pairs = [(float(p[cost]), float(p[error])) for p in points]
    front = non_dominated(pairs)
    figure, axes = plt.subplots(figsize=(6.4, 4.4))
    axes.plot(
        [pairs[i][0] for i in front],
        [pairs[i][1] for i in front],
        "-",
        color="0.6",
        zorder=1,
        label="front (non-dominated)",
    )
    for i, (point, (x, y)) in enumerate(zip(points, pairs, strict=True)):
        default = bool(point.get("default"))
        axes.scatter(
            [x],
            [y],
            marker="*" if default else "o",
            s=180 if default else 40,
            color="tab:red" if default else ("tab:blue" if i in front else "0.5"),
            zorder=3,
        )
        axes.annotate(
            label(point) + (" (default)" if default else ""),
            (x, y),
            textcoords="offset points",
            xytext=(5, 4),
            fontsize=7,
        )
    if logx:
        axes.set_xscale("log")
    if logy:
        positive = [y for _, y in pairs if y > 0]
        if len(positive) == len(pairs):
            axes.set_yscale("log")
        else:  # a zero error (the reference itself) stays on the plot
            axes.set_yscale("symlog", linthresh=min(positive, default=1.0) / 2)
    axes.set_xlabel(xlabel)
    axes.set_ylabel(ylabel)
    axes.set_title(title, fontsize=10)
    if note:
        figure.text(0.01, 0.01, note, fontsize=6, color="0.3")
    axes.legend(fontsize=7, loc="best")
    axes.margins(x=0.15, y=0.12)
    axes.grid(alpha=0.3)
    figure.tight_layout(rect=(0, 0.03, 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return front
