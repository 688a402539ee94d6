"""Stage compare_domains: the realism statistics of several frame sets side by side
(dali_cli.reporting.domains), printed, and with an output directory also as JSON and plots."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dali_cli.store.manifest import StageOutcome, run_stage

STATS_NAME = "domains.json"


def domain_stats(
    directory: str | Path,
    view_deg: float | None,
    label: str = "Car",
    max_frames: int | None = None,
    seed: int = 0,
):
    """DomainStats of the frame set `directory` (its boxes.parquet rows labelled `label` as the
    cars; no box table: no cars), over its first `max_frames` frames (all when None)."""
    from dali_cli.reporting.domains import frame_stats, summarize
    from dali_cli.store.artifacts import BOXES_NAME, FrameSet, read_boxes

    frames = FrameSet(directory)
    boxes_path = Path(directory) / BOXES_NAME
    table = read_boxes(directory) if boxes_path.is_file() else None
    by_frame = {}
    if table is not None and len(table):
        table = table.select(table["label"].astype(str) == label)
        by_frame = table.rows_by_frame()
    rng = np.random.default_rng(seed)
    count = len(frames) if max_frames is None else min(len(frames), max_frames)
    material = []
    for frame_id, points in frames.iter_frames(range(count)):
        rows = by_frame.get(frame_id)
        boxes = table.boxes[rows] if rows is not None else np.zeros((0, 7))
        material.append(frame_stats(points, boxes, view_deg, rng))
    return summarize(material)


def _plain(value):
    """A statistic as JSON has it: NaN (no frames) as null."""
    return None if isinstance(value, float) and np.isnan(value) else value


def _document(names: list[str], paths: list[Path], stats: list, settings: dict) -> dict:
    return {
        "settings": settings,
        "domains": {
            name: {"path": str(path), **{k: _plain(v) for k, v in domain.values.items()}}
            for name, path, domain in zip(names, paths, stats, strict=True)
        },
    }


def compare_domains(
    named_paths: list[tuple[str, Path]],
    *,
    view_deg: float | None,
    label: str = "Car",
    max_frames: int | None = None,
    out: str | Path | None = None,
    force: bool = False,
) -> tuple[dict, StageOutcome | None]:
    """Statistics of every (name, frame set); with `out`, a directory holding domains.json and
    the distribution plots (written atomically with a manifest). Returns (document, outcome)."""
    from dali_cli.reporting.domains import plot_domains

    names = [name for name, _ in named_paths]
    paths = [Path(path) for _, path in named_paths]
    stats = [domain_stats(path, view_deg, label, max_frames) for path in paths]
    settings = {"view_deg": view_deg, "label": label, "max_frames": max_frames}
    document = _document(names, paths, stats, settings)
    if out is None:
        return document, None

    def build(tmp: Path):
        (tmp / STATS_NAME).write_text(json.dumps(document, indent=2) + "\n")
        written = plot_domains(list(zip(names, stats, strict=True)), tmp)
        return {"counts": {"domains": len(names), "plots": len(written)}}

    outcome = run_stage(
        "compare-domains",
        out,
        {f"domain_{k}": path for k, path in enumerate(paths)},
        {**settings, "names": names},
        build,
        force=force,
    )
    return document, outcome
