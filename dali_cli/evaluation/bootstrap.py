"""Paired bootstrap over evaluation frames: how much of a difference in AP between predictions on
the same frames comes from which frames were drawn.

A difference between two rows of a benchmark has two sources of chance: the training (seeds,
which `dali report` aggregates) and the validation frames. With 200 frames AP_3D@0.7 moves in
steps: resizing every box by 3 mm in height moved one control by 1.4 AP_3D (docs/evaluation.md),
because a few near cars sit at IoU ≈ 0.7. The bootstrap draws the evaluation frames
with replacement (the same draw for every row: paired), evaluates each row on the draw with the
full KITTI-protocol code (`dali_cli.evaluation.evaluate.evaluate`, thresholds and all) and reports the spread
of each row's AP and of its difference to the first row.

Frames are the unit (the boxes of one frame are not independent). A frame drawn twice enters twice,
under two new ids. The frame universe is the union of the frames of the truth and of every row, as
`dali eval` takes it for tables.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dali_cli.store.artifacts import BoxTable

Metric = Callable[[BoxTable, BoxTable], dict[str, float]]  # (pred, gt) -> {name: AP}


class FrameIndex:
    """The rows of one table grouped by the frames of a universe, for fast resampling.

    universe: (F,) str frame ids; `rows(draw)` for a draw (K,) of universe positions returns the
    table's rows of those frames (frame by frame, a frame drawn twice twice) and the new frame id of
    each row: the position in the draw ("0" ... "K-1")."""

    def __init__(self, table: BoxTable, universe: np.ndarray):
        position = {frame: k for k, frame in enumerate(universe)}
        frame_of_row = np.array([position[str(f)] for f in table.frame_id], np.int64)
        self.order = np.argsort(frame_of_row, kind="stable")  # rows sorted by frame position
        self.counts = np.bincount(frame_of_row, minlength=len(universe))  # (F,)
        self.starts = np.r_[0, np.cumsum(self.counts)[:-1]]  # (F,) into `order`

    def rows(self, draw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row indices (R,), new frame ids (R,) str) of the frames `draw` (K,)."""
        counts = self.counts[draw]
        total = int(counts.sum())
        first = np.repeat(self.starts[draw] - np.r_[0, np.cumsum(counts)[:-1]], counts)
        rows = self.order[first + np.arange(total)]
        return rows, np.repeat(np.arange(len(draw)), counts).astype(str).astype(object)


def resampled(table: BoxTable, index: FrameIndex, draw: np.ndarray) -> BoxTable:
    """`table` restricted to the frames of `draw`, each drawn frame under its draw position."""
    rows, frame_ids = index.rows(draw)
    return table.select(rows).with_columns(frame_id=frame_ids)


def frame_universe(gt: BoxTable, preds: list[BoxTable]) -> np.ndarray:
    """(F,) sorted str: every frame of the truth and of the predictions."""
    frames = [np.asarray(t.frame_id).astype(str) for t in (gt, *preds)]
    return np.unique(np.concatenate(frames)) if frames else np.zeros(0, str)


@dataclass
class BootstrapResult:
    """names (P,) of the rows, the first the reference; metric names (M,); full (P, M) AP on all
    frames; samples (S, P, M) AP on each draw (NaN where a draw leaves a metric undefined)."""

    names: list[str]
    metrics: list[str]
    full: np.ndarray
    samples: np.ndarray
    frames: int
    seed: int

    def summary(self) -> dict:
        """Per row and metric: AP on all frames, the bootstrap std of AP, and (rows after the
        first) the difference to the first row on all frames, its bootstrap std, its 2.5 / 97.5
        percentiles and the share of draws where it is <= 0."""
        rows = {}
        for p, name in enumerate(self.names):
            block = {}
            for m, metric in enumerate(self.metrics):
                entry = {
                    "ap": _number(self.full[p, m]),
                    "std": _number(_std(self.samples[:, p, m])),
                }
                if p > 0:
                    delta = self.samples[:, p, m] - self.samples[:, 0, m]
                    delta = delta[np.isfinite(delta)]
                    entry["delta"] = _number(self.full[p, m] - self.full[0, m])
                    entry["delta_std"] = _number(_std(delta))
                    low, high = np.percentile(delta, [2.5, 97.5]) if len(delta) else (np.nan,) * 2
                    entry["delta_interval_95"] = [_number(low), _number(high)]
                    entry["share_not_above_reference"] = (
                        _number(float(np.mean(delta <= 0))) if len(delta) else None
                    )
                block[metric] = entry
            rows[name] = block
        return {
            "reference": self.names[0],
            "frames": self.frames,
            "samples": int(self.samples.shape[0]),
            "seed": self.seed,
            "rows": rows,
        }


def _std(values: np.ndarray) -> float:
    values = values[np.isfinite(values)]
    return float(np.std(values, ddof=1)) if len(values) > 1 else float("nan")


def _number(value) -> float | None:
    return round(float(value), 4) if value is not None and np.isfinite(value) else None


def paired_bootstrap(
    preds: dict[str, BoxTable],
    gt: BoxTable,
    metric: Metric,
    samples: int = 1000,
    seed: int = 0,
    progress: Callable[[int], None] | None = None,
) -> BootstrapResult:
    """Evaluate every table of `preds` (name -> table; the first is the reference) against `gt`
    on all frames and on `samples` draws of the frame universe with replacement (the same draws
    for every table), with `metric(pred, gt) -> {name: AP or None}`. Seeded: the same `seed`
    gives the same draws."""
    if not preds:
        raise ValueError("no predictions to compare")
    if samples < 2:
        raise ValueError(f"samples must be at least 2, got {samples}")
    names = list(preds)
    universe = frame_universe(gt, list(preds.values()))
    indices = {name: FrameIndex(table, universe) for name, table in preds.items()}
    gt_index = FrameIndex(gt, universe)
    first = {name: metric(table, gt) for name, table in preds.items()}
    metric_names = list(first[names[0]])
    full = np.array([[_value(first[n].get(m)) for m in metric_names] for n in names])
    rng = np.random.default_rng(seed)
    values = np.full((samples, len(names), len(metric_names)), np.nan)
    for s in range(samples):
        draw = rng.integers(0, len(universe), len(universe))
        truth = resampled(gt, gt_index, draw)
        for p, name in enumerate(names):
            result = metric(resampled(preds[name], indices[name], draw), truth)
            values[s, p] = [_value(result.get(m)) for m in metric_names]
        if progress is not None:
            progress(1)
    return BootstrapResult(names, metric_names, full, values, len(universe), seed)


def _value(ap) -> float:
    return float("nan") if ap is None else float(ap)
