"""The real-target table of `make real-kitti` (markdown): every row's KITTI AP on the drive's
tracklets (transductive) and on the labelled object frames (inductive), the mean predicted size
against the labels', the pseudo labels' precision and recall on the drive (by score band, and
where the false boxes lie), and each stage's wall time.

    .venv/bin/python bench/real_kitti_table.py RUN [--out RUN/real-kitti.md]

A diagnostic: it reads the drive's labels (RUN/data/drive_labels), which no DALI stage does.
Pseudo-label truth: the drive's cars with at least --min-points points inside the detection grid;
a pseudo box is a true positive at BEV IoU > --iou with a not yet matched car (greedy by score).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from pseudo_labels import HALLUCINATED_M, in_grid, match  # noqa: E402

from dali_cli.geometry import point_box_indices  # noqa: E402
from dali_cli.store.artifacts import FrameSet, read_boxes  # noqa: E402

# row name, its drive evaluation, its object-frame evaluation
ROWS = (
    ("source only", "iter0/eval", "objects/source"),
    ("PTSN only", "iter0/eval_ptsn", "objects/ptsn"),
    ("DALI x1", "iter1/eval", "objects/x1"),
    ("DALI x2", "iter2/eval", "objects/x2"),
    ("DALI x2 + ST", "iter2_st/eval", "objects/x2_st"),
    (
        "control (source, x2 budget, PTSN)",
        "baselines/source_x2_budget/eval_ptsn",
        "objects/control",
    ),
    ("sim oracle (x2 budget)", "baselines/sim_oracle_x2_budget/eval", "objects/oracle"),
)
LEVELS = ("easy", "moderate", "hard")
SCORE_BANDS = ((0.3, 0.4), (0.4, 0.5), (0.5, 0.6), (0.6, 0.8), (0.8, 1.01))
FLAT_M = 0.5  # a box whose points span less height than this holds road, curb or clutter


def read_json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def ap_cells(metrics: dict | None) -> list[str]:
    """AP_BEV, AP_3D at 0.7 (easy, moderate, hard), then at 0.5 (moderate) as text cells."""
    if metrics is None:
        return ["-"] * 8
    strict, loose = metrics["Car"], metrics.get("Car@0.5", {})
    cells = [f"{strict[kind][level]:.1f}" for kind in ("bev", "3d") for level in LEVELS]
    cells += [f"{loose[kind]['moderate']:.1f}" if loose else "-" for kind in ("bev", "3d")]
    return cells


def size_cell(metrics: dict | None) -> str:
    if metrics is None or not metrics.get("sizes", {}).get("pred"):
        return "-"
    return " × ".join(f"{v:.2f}" for v in metrics["sizes"]["pred"])


def ap_table(run: Path, column: int) -> list[str]:
    header = (
        "| row | BEV@0.7 E | M | H | 3D@0.7 E | M | H | BEV@0.5 M | 3D@0.5 M | mean l × w × h "
        "(score ≥ 0.3) | scale |"
    )
    lines = [header, "|" + "---|" * 11]
    truth = None
    for name, *paths in ROWS:
        metrics = read_json(run / paths[column] / "metrics.json")
        if metrics is not None and truth is None:
            truth = metrics["sizes"]["gt"]
        scale = f"{metrics['scale']:.3f}" if metrics and metrics.get("scale") else "-"
        cells = [name, *ap_cells(metrics), size_cell(metrics), scale]
        lines.append("| " + " | ".join(cells) + " |")
    if truth:
        lines.append("")
        lines.append("Labelled cars' mean l × w × h: " + " × ".join(f"{v:.2f}" for v in truth))
    return lines


def pseudo_label_quality(pseudo_dir: Path, truth, frames: FrameSet, iou: float, min_points: int):
    """Precision / recall of one pseudo-label set, by score band, and where false boxes lie."""
    pseudo = read_boxes(pseudo_dir)
    truth_rows, pseudo_rows = truth.rows_by_frame(), pseudo.rows_by_frame()
    hits, scores, near, flat, ranges, found, true_ranges = [], [], [], [], [], [], []
    for frame_id in sorted(set(truth_rows) | set(pseudo_rows)):
        cars = truth.boxes[truth_rows.get(frame_id, np.zeros(0, np.int64))]
        counts = truth["num_points"][truth_rows.get(frame_id, np.zeros(0, np.int64))]
        counted = cars[in_grid(cars) & (counts >= min_points)]
        rows = pseudo_rows.get(frame_id, np.zeros(0, np.int64))
        boxes, score = pseudo.boxes[rows], pseudo["score"][rows]
        keep = in_grid(boxes)
        boxes, score = boxes[keep], score[keep]
        matched = match(boxes, score, counted, iou)
        hit = np.zeros(len(counted), bool)
        hit[matched[matched >= 0]] = True
        found.append(hit)
        true_ranges.append(np.hypot(counted[:, 0], counted[:, 1]))
        gaps = np.linalg.norm(boxes[:, None, :2] - cars[None, :, :2], axis=2)
        near.append(gaps.min(axis=1) < HALLUCINATED_M if len(cars) else np.zeros(len(boxes), bool))
        points = frames.frame(frame_id)
        owner = point_box_indices(points, boxes)
        spans = np.zeros(len(boxes))
        for index in range(len(boxes)):
            z = points[owner == index, 2]
            spans[index] = z.max() - z.min() if len(z) else 0.0
        flat.append(spans < FLAT_M)
        hits.append(matched >= 0)
        scores.append(score)
        ranges.append(np.hypot(boxes[:, 0], boxes[:, 1]))
    hit, score = np.concatenate(hits), np.concatenate(scores)
    near, flat, rng = np.concatenate(near), np.concatenate(flat), np.concatenate(ranges)
    found, true_ranges = np.concatenate(found), np.concatenate(true_ranges)
    bands = []
    for low, high in SCORE_BANDS:
        chosen = (score >= low) & (score < high)
        kept = score >= low
        bands.append(
            {
                "band": f"{low:.1f}-{min(high, 1.0):.1f}",
                "boxes": int(chosen.sum()),
                "precision": float(hit[chosen].mean()) if chosen.any() else None,
                "precision_at_or_above": float(hit[kept].mean()) if kept.any() else None,
                "recall_at_or_above": float(hit[kept].sum() / max(len(found), 1)),
            }
        )
    false = ~hit
    return {
        "frames": len(truth_rows | pseudo_rows),
        "boxes": int(len(hit)),
        "cars": int(len(found)),
        "precision": float(hit.mean()) if len(hit) else None,
        "recall": float(found.mean()) if len(found) else None,
        "recall_0_30": float(found[true_ranges < 30].mean()) if (true_ranges < 30).any() else None,
        "bands": bands,
        "false": {
            "boxes": int(false.sum()),
            "near_a_car": int((false & near).sum()),
            "flat_away_from_cars": int((false & ~near & flat).sum()),
            "tall_away_from_cars": int((false & ~near & ~flat).sum()),
            "within_20_m": int((false & (rng < 20)).sum()),
            "20_to_40_m": int((false & (rng >= 20) & (rng < 40)).sum()),
            "beyond_40_m": int((false & (rng >= 40)).sum()),
        },
    }


def pct(value) -> str:
    return "-" if value is None else f"{100 * value:.0f} %"


def pseudo_section(run: Path, iou: float, min_points: int) -> tuple[list[str], dict]:
    truth = read_boxes(run / "data/drive_labels")
    truth = truth.select(np.asarray(truth["label"]).astype(str) == "Car")
    frames = FrameSet(run / "data/drive")
    lines = [
        f"Drive cars in the detection grid with ≥ {min_points} points; a match is BEV IoU > {iou:g}.",
        "",
        "| pseudo labels | boxes | boxes / frame | cars | precision | recall | recall < 30 m |",
        "|---|---|---|---|---|---|---|",
    ]
    results = {}
    for name in ("iter1", "iter2", "iter3"):
        directory = run / name / "pseudo"
        if not (directory / "manifest.json").is_file():
            continue
        result = pseudo_label_quality(directory, truth, frames, iou, min_points)
        results[name] = result
        per_frame = result["boxes"] / max(result["frames"], 1)
        lines.append(
            f"| {name}/pseudo | {result['boxes']} | {per_frame:.1f} | {result['cars']} | "
            f"{pct(result['precision'])} | {pct(result['recall'])} | {pct(result['recall_0_30'])} |"
        )
    for name, result in results.items():
        lines += [
            "",
            f"{name}/pseudo by score band (precision in the band; P and R at or above it):",
            "",
        ]
        lines += ["| score | boxes | precision | P ≥ | R ≥ |", "|---|---|---|---|---|"]
        for band in result["bands"]:
            lines.append(
                f"| {band['band']} | {band['boxes']} | {pct(band['precision'])} | "
                f"{pct(band['precision_at_or_above'])} | {pct(band['recall_at_or_above'])} |"
            )
        false = result["false"]
        lines += [
            "",
            f"{name}/pseudo false boxes: {false['boxes']}; within {HALLUCINATED_M:g} m of a labelled "
            f"car {false['near_a_car']}; away from cars and flat (their points span < {FLAT_M} m "
            f"of height: road, curb, low clutter) {false['flat_away_from_cars']}; away from cars "
            f"and taller {false['tall_away_from_cars']}; by range: < 20 m {false['within_20_m']}, "
            f"20-40 m {false['20_to_40_m']}, ≥ 40 m {false['beyond_40_m']}.",
        ]
    return lines, results


def wall_times(run: Path) -> list[str]:
    lines = ["| stage output | wall s |", "|---|---|"]
    total = 0.0
    for manifest in sorted(run.rglob("manifest.json")):
        data = read_json(manifest)
        seconds = (data or {}).get("timings", {}).get("wall_seconds")
        if seconds is None:
            continue
        total += seconds
        lines.append(f"| {manifest.parent.relative_to(run)} | {seconds:.0f} |")
    lines.append(f"| all stages | {total:.0f} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--iou", type=float, default=0.5)
    parser.add_argument("--min-points", type=int, default=5)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    run = args.run
    lines = ["## On the drive's tracklets (transductive, KITTI R40, Car)", ""]
    lines += ap_table(run, 0)
    lines += ["", "## On the labelled KITTI object frames (inductive, KITTI R40, Car)", ""]
    lines += ap_table(run, 1)
    lines += ["", "## Pseudo labels on the drive", ""]
    pseudo_lines, results = pseudo_section(run, args.iou, args.min_points)
    lines += pseudo_lines
    lines += ["", "## Wall time per stage", ""] + wall_times(run)
    text = "\n".join(lines) + "\n"
    if args.out:
        args.out.write_text(text)
        args.out.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
    print(text)


if __name__ == "__main__":
    main()
