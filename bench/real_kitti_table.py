"""The real-target table of `make real-kitti` (markdown) over one run per seed: every row's KITTI
AP (Car, R40, moderate) on each evaluation set as mean ± std over the seeds, every row minus the
equal-budget control paired by seed, each DALI row minus its own control paired by seed (x2 − control,
x2 + ST − control + ST, x2 + tracked ST − control + tracked ST), where each row loses AP@0.7
(`dali eval`'s error breakdown: the AP with each kind of error fixed), `dali compare`'s paired
bootstrap over the frames for the same pairs, the pseudo labels' precision and recall on the
labelled drive (by score band, and where the false boxes lie) and each stage's wall time.

    .venv/bin/python bench/real_kitti_table.py RUN-s0 RUN-s1 RUN-s2 --data REAL_DATA \
        [--sets drive objects_adapted objects_other] [--out REPORT/real-kitti.md]

Sets: `drive` is the labelled drive (REAL_DATA/drive_labels, the rows' drive evaluations); any
other name is an object-frame set REAL_DATA/<set> evaluated into RUN/<set>/<row>.
A diagnostic: it reads the drive's labels, which no DALI stage does. Pseudo-label truth: the
drive's cars with at least --min-points points inside the detection grid; a pseudo box is a true
positive at BEV IoU > --iou with a not yet matched car (greedy by score).
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

from dali_cli.evaluation.evaluate import ap_ceiling, evaluate  # noqa: E402
from dali_cli.geometry import point_box_indices  # noqa: E402
from dali_cli.store.artifacts import BoxTable, FrameSet, read_boxes  # noqa: E402

# row name, its drive evaluation, its name on the object sets (RUN/<set>/<name>)
ROWS = (
    ("source only", "iter0/eval", "source"),
    ("PTSN only", "iter0/eval_ptsn", "ptsn"),
    ("DALI x1", "iter1/eval", "x1"),
    ("DALI x2", "iter2/eval", "x2"),
    ("DALI x2 + ST", "iter2_st/eval", "x2_st"),
    ("control (source, x2 budget, PTSN)", "baselines/source_x2_budget/eval_ptsn", "control"),
    ("control + ST", "baselines/source_x2_budget_st/eval", "control_st"),
    ("DALI x2 + tracked ST", "iter2_tst/eval", "x2_tst"),
    ("control + tracked ST", "baselines/source_x2_budget_tst/eval", "control_tst"),
    ("control + tracked ST ×2", "baselines/source_x2_budget_tst2/eval", "control_tst2"),
    ("sim oracle (x2 budget)", "baselines/sim_oracle_x2_budget/eval", "oracle"),
)
CONTROL = "control"
# `dali compare` files (RUN/compare_real/<set>-<row>.json): the row against its reference
PAIRS = (("x2", "control"), ("x2_st", "control_st"), ("x2_tst", "control_tst"))
# (metric key, IoU key in metrics.json, header)
METRICS = (
    ("bev", "Car", "BEV@0.7"),
    ("3d", "Car", "3D@0.7"),
    ("bev", "Car@0.5", "BEV@0.5"),
    ("3d", "Car@0.5", "3D@0.5"),
)
SCORE_BANDS = ((0.3, 0.4), (0.4, 0.5), (0.5, 0.6), (0.6, 0.8), (0.8, 1.01))
FLAT_M = 0.5  # a box whose points span less height than this holds road, curb or clutter
SET_TITLES = {
    "drive": "the labelled drive's tracklets",
    "objects_adapted": "labelled object frames of the target's drives (transductive)",
    "objects_other": "labelled object frames of other drives (inductive)",
    "objects": "labelled object frames",
}


def read_json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def metrics_of(run: Path, set_name: str, row: tuple[str, str, str]) -> dict | None:
    """A row's metrics.json on a set, or None when it was not evaluated (yet)."""
    directory = run / row[1] if set_name == "drive" else run / set_name / row[2]
    return read_json(directory / "metrics.json")


def moderate(metrics: dict | None, kind: str, block: str) -> float | None:
    if metrics is None or block not in metrics:
        return None
    return float(metrics[block][kind]["moderate"])


def spread(values: list[float], sign: str = "") -> str:
    """`mean ± std` (sample std) of the values there are (`sign="+"`: signed), `-` when none."""
    if not values:
        return "-"
    mean = f"{np.mean(values):{sign}.1f}"
    return mean if len(values) == 1 else f"{mean} ± {np.std(values, ddof=1):.1f}"


def ap_table(runs: list[Path], set_name: str) -> list[str]:
    """Each row's moderate AP over the seeds, then the per-seed BEV / 3D at 0.7."""
    headers = [header for _, _, header in METRICS]
    lines = [
        "| row | " + " | ".join(headers) + " | per seed BEV / 3D @0.7 |",
        "|---|" + "---|" * (len(headers) + 1),
    ]
    for row in ROWS:
        found = [metrics_of(run, set_name, row) for run in runs]
        cells = []
        for kind, block, _ in METRICS:
            values = [moderate(m, kind, block) for m in found]
            cells.append(spread([v for v in values if v is not None]))
        per_seed = " · ".join(
            "-"
            if m is None
            else f"{moderate(m, 'bev', 'Car'):.1f} / {moderate(m, '3d', 'Car'):.1f}"
            for m in found
        )
        lines.append(f"| {row[0]} | " + " | ".join(cells) + f" | {per_seed} |")
    return lines


def seed_deltas(runs: list[Path], set_name: str, row, reference, kind: str, block: str):
    """`row` minus `reference` in each run (moderate AP), None where either was not evaluated."""
    deltas = []
    for run in runs:
        mine = moderate(metrics_of(run, set_name, row), kind, block)
        theirs = moderate(metrics_of(run, set_name, reference), kind, block)
        deltas.append(None if mine is None or theirs is None else mine - theirs)
    return deltas


def signed(delta: float | None) -> str:
    return "-" if delta is None else f"{delta:+.1f}"


def paired_table(runs: list[Path], set_name: str) -> list[str]:
    """Every row minus the control, seed by seed (only seeds where both were evaluated)."""
    control = next(row for row in ROWS if row[2] == CONTROL)
    headers = [header for _, _, header in METRICS]
    lines = [
        "| row − control | " + " | ".join(headers) + " | per seed BEV@0.7 |",
        "|---|" + "---|" * (len(headers) + 1),
    ]
    for row in ROWS:
        if row is control:
            continue
        cells = []
        for kind, block, _ in METRICS:
            deltas = seed_deltas(runs, set_name, row, control, kind, block)
            cells.append(spread([d for d in deltas if d is not None], sign="+"))
        per_seed = [signed(d) for d in seed_deltas(runs, set_name, row, control, "bev", "Car")]
        lines.append(f"| {row[0]} | " + " | ".join(cells) + f" | {' · '.join(per_seed)} |")
    return lines


def dali_pairs_table(runs: list[Path], set_name: str) -> list[str]:
    """Each DALI row minus its own control (`PAIRS`), seed by seed: mean ± std of Δ AP@0.7."""
    by_name = {row[2]: row for row in ROWS}
    lines = [
        "| DALI row − its control | Δ BEV@0.7 | Δ 3D@0.7 | per seed Δ BEV / Δ 3D |",
        "|---|---|---|---|",
    ]
    for name, reference in PAIRS:
        row, control = by_name[name], by_name[reference]
        bev = seed_deltas(runs, set_name, row, control, "bev", "Car")
        d3d = seed_deltas(runs, set_name, row, control, "3d", "Car")
        per_seed = " · ".join(f"{signed(a)} / {signed(b)}" for a, b in zip(bev, d3d, strict=True))
        cells = [spread([d for d in deltas if d is not None], "+") for deltas in (bev, d3d)]
        lines.append(f"| {row[0]} − {control[0]} | {cells[0]} | {cells[1]} | {per_seed} |")
    return lines


def predictions_of(run: Path, set_name: str, row: tuple[str, str, str]) -> Path:
    directory = run / row[1] if set_name == "drive" else run / set_name / row[2]
    return directory / "predictions.parquet"


def r400_at_07(predictions: BoxTable, truth: BoxTable, protocol: str = "kitti") -> tuple:
    """(AP_BEV, AP_3D) @0.7 under R400 (the precision at exact recalls) of the headline group:
    KITTI moderate, or all ranges under the range protocol."""
    car = evaluate(predictions, truth, 0.7, 400, protocol)["Car"]
    group = "moderate" if "moderate" in car["bev"] else "all"
    return car["bev"][group], car["3d"][group]


def exact_recall_section(runs: list[Path], set_name: str, data: Path) -> list[str]:
    """Where too few cars count for KITTI's R40 to reach 100 (`ap_ceiling`): every row's AP@0.7
    under R400, recomputed from its saved predictions, over the seeds and for the DALI pairs;
    nothing when the set is large enough."""
    counted = next(
        (gt for run in runs for row in ROWS
         if (gt := (metrics_of(run, set_name, row) or {}).get("Car", {}).get("counts", {})
             .get("moderate", {}).get("gt")) is not None),
        None,
    )  # fmt: skip
    ceiling = ap_ceiling(counted, 40) if counted else None
    if ceiling is None or ceiling >= 100.0:
        return []
    truth = read_boxes(data / ("drive_labels" if set_name == "drive" else set_name))
    values = {  # (row name, run) -> (BEV, 3D) AP_R400@0.7 moderate
        (row[2], run): r400_at_07(read_boxes(path), truth)
        for row in ROWS
        for run in runs
        if (path := predictions_of(run, set_name, row)).is_file()
    }
    lines = [
        f"Only {counted} moderate cars count here, so KITTI's R40 caps AP at {ceiling:.1f} (what "
        "a perfect detector scores). The same predictions under R400 (the precision at exact "
        "recalls, `dali eval --recall-positions 400`), AP_BEV / AP_3D@0.7:",
        "",
        "| row | R400 BEV / 3D@0.7 | per seed |",
        "|---|---|---|",
    ]
    for row in ROWS:
        found = [values.get((row[2], run)) for run in runs]
        have = [v for v in found if v is not None]
        if not have:
            continue
        cells = " / ".join(spread([v[k] for v in have]) for k in (0, 1))
        per_seed = " · ".join("-" if v is None else f"{v[0]:.1f} / {v[1]:.1f}" for v in found)
        lines.append(f"| {row[0]} | {cells} | {per_seed} |")
    by_name = {row[2]: row for row in ROWS}
    for name, reference in PAIRS:
        pairs = [(values.get((name, r)), values.get((reference, r))) for r in runs]
        deltas = [(a[0] - b[0], a[1] - b[1]) for a, b in pairs if a is not None and b is not None]
        if deltas:
            cells = " / ".join(spread([d[k] for d in deltas], "+") for k in (0, 1))
            per_seed = " · ".join(f"{d[0]:+.1f} / {d[1]:+.1f}" for d in deltas)
            label = f"{by_name[name][0]} − {by_name[reference][0]}"
            lines.append(f"| {label} | {cells} | {per_seed} |")
    return lines


FIXES = ("mislocalized", "background", "duplicate", "missed")


def loss_table(runs: list[Path], set_name: str) -> list[str]:
    """Where each row loses AP@0.7 (moderate): the AP gained with each kind of error fixed alone
    (`dali eval`'s breakdown, `ap_fixed` − `ap`), mean over the seeds, BEV / 3D, and the largest."""
    lines = [
        "| row | AP BEV / 3D@0.7 | "
        + " | ".join(f"+ {fix} fixed" for fix in FIXES)
        + " | largest loss (3D) |",
        "|---|---|" + "---|" * (len(FIXES) + 1),
    ]
    for row in ROWS:
        blocks = []
        for run in runs:
            errors = (metrics_of(run, set_name, row) or {}).get("errors") or {}
            block = (errors.get("false_positives") or {}).get("0.7")
            if block is not None:
                blocks.append(block)
        if not blocks:
            continue
        ap = {kind: np.mean([b[kind]["ap"] for b in blocks]) for kind in ("bev", "3d")}
        gain = {
            (fix, kind): np.mean([b[kind]["ap_fixed"][fix] - b[kind]["ap"] for b in blocks])
            for fix in FIXES
            for kind in ("bev", "3d")
        }
        largest = max(FIXES, key=lambda fix: gain[(fix, "3d")])
        cells = [f"{gain[(fix, 'bev')]:+.1f} / {gain[(fix, '3d')]:+.1f}" for fix in FIXES]
        lines.append(
            f"| {row[0]} | {ap['bev']:.1f} / {ap['3d']:.1f} | "
            + " | ".join(cells)
            + f" | {largest} ({gain[(largest, '3d')]:+.1f}) |"
        )
    return lines


def bootstrap_table(runs: list[Path], sets: list[str]) -> list[str]:
    """`dali compare`'s paired bootstrap per set, pair and seed: Δ AP (moderate, IoU 0.7) ± the
    bootstrap std, its 95 % interval and P(Δ ≤ 0)."""
    lines = [
        "| set | row − reference | seed | Δ BEV ± std | 95 % | P(Δ≤0) | Δ 3D ± std | 95 % | P(Δ≤0) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for set_name in sets:
        for row, reference in PAIRS:
            for run in runs:
                document = read_json(run / "compare_real" / f"{set_name}-{row}.json")
                if document is None:
                    continue
                entry = document["bootstrap"]["rows"][row]
                cells = []
                for kind in ("bev", "3d"):
                    metric = entry.get(f"{kind} moderate")
                    if metric is None or metric.get("delta") is None:
                        cells += ["-", "-", "-"]
                        continue
                    low, high = metric["delta_interval_95"]
                    cells += [
                        f"{metric['delta']:+.1f} ± {metric['delta_std']:.1f}",
                        f"[{low:+.1f}, {high:+.1f}]",
                        f"{metric['share_not_above_reference']:.2f}",
                    ]
                lines.append(
                    f"| {set_name} | {row} − {reference} | {run.name} | " + " | ".join(cells) + " |"
                )
    return lines


def pseudo_label_quality(pseudo_dir: Path, truth, frames: FrameSet, iou: float, min_points: int):
    """Precision / recall of one pseudo-label set on the labelled frames `frames` (a target of
    several drives is pseudo-labelled on all of them), by score band, and where false boxes lie."""
    pseudo = read_boxes(pseudo_dir)
    pseudo = pseudo.select(np.isin(pseudo.frame_id.astype(str), frames.frame_ids))
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


PSEUDO_SETS = (
    "iter1/pseudo",
    "iter2/pseudo",
    "iter3/pseudo",
    "baselines/source_x2_budget/pseudo",
    "iter3/tracked",
    "baselines/source_x2_budget/tracked",
)


def pseudo_section(
    runs: list[Path], data: Path, iou: float, min_points: int
) -> tuple[list[str], dict]:
    """The pseudo labels of every run on the labelled drive's frames (none where the target does
    not hold them: a run adapted without the drive, as `make real-kitti-holdout`'s)."""
    frames = FrameSet(data / "drive_labels")
    target = data / "target"
    if target.is_dir() and not set(FrameSet(target).frame_ids) & set(frames.frame_ids):
        note = f"None: the target ({target}) holds none of the labelled drive's frames."
        return [note], {}
    truth = read_boxes(data / "drive_labels")
    truth = truth.select(np.asarray(truth["label"]).astype(str) == "Car")
    lines = [
        f"Drive cars in the detection grid with ≥ {min_points} points; a match is BEV IoU > {iou:g}.",
        "",
        "| run | pseudo labels | boxes | boxes / frame | cars | precision | recall | recall < 30 m |",
        "|---|---|---|---|---|---|---|---|",
    ]
    results = {}
    for run in runs:
        for name in PSEUDO_SETS:
            directory = run / name
            if not (directory / "manifest.json").is_file():
                continue
            result = pseudo_label_quality(directory, truth, frames, iou, min_points)
            results[f"{run.name}/{name}"] = result
            per_frame = result["boxes"] / max(len(frames), 1)
            lines.append(
                f"| {run.name} | {name} | {result['boxes']} | {per_frame:.1f} | {result['cars']} | "
                f"{pct(result['precision'])} | {pct(result['recall'])} | {pct(result['recall_0_30'])} |"
            )
    for name, result in results.items():
        lines += ["", f"{name} by score band (precision in the band; P and R at or above it):", ""]
        lines += ["| score | boxes | precision | P ≥ | R ≥ |", "|---|---|---|---|---|"]
        for band in result["bands"]:
            lines.append(
                f"| {band['band']} | {band['boxes']} | {pct(band['precision'])} | "
                f"{pct(band['precision_at_or_above'])} | {pct(band['recall_at_or_above'])} |"
            )
        false = result["false"]
        lines += [
            "",
            f"{name} false boxes: {false['boxes']}; within {HALLUCINATED_M:g} m of a labelled "
            f"car {false['near_a_car']}; away from cars and flat (their points span < {FLAT_M} m "
            f"of height: road, curb, low clutter) {false['flat_away_from_cars']}; away from cars "
            f"and taller {false['tall_away_from_cars']}; by range: < 20 m {false['within_20_m']}, "
            f"20-40 m {false['20_to_40_m']}, ≥ 40 m {false['beyond_40_m']}.",
        ]
    return lines, results


def wall_times(runs: list[Path], data: Path) -> list[str]:
    """Each stage's wall time per run (the shared data once) and the totals."""
    lines = ["| stage output | " + " | ".join(run.name for run in runs) + " |"]
    lines.append("|---|" + "---|" * len(runs))
    seconds: dict[str, dict[int, float]] = {}
    for column, run in enumerate(runs):
        for manifest in sorted(run.rglob("manifest.json")):
            wall = ((read_json(manifest) or {}).get("timings") or {}).get("wall_seconds")
            if wall is not None:
                seconds.setdefault(str(manifest.parent.relative_to(run)), {})[column] = wall
    for stage, by_run in seconds.items():
        cells = [f"{by_run[c]:.0f}" if c in by_run else "-" for c in range(len(runs))]
        lines.append(f"| {stage} | " + " | ".join(cells) + " |")
    totals = [sum(by_run.get(c, 0.0) for by_run in seconds.values()) for c in range(len(runs))]
    lines.append("| all stages | " + " | ".join(f"{t:.0f}" for t in totals) + " |")
    shared = sum(
        ((read_json(m) or {}).get("timings") or {}).get("wall_seconds") or 0.0
        for m in data.rglob("manifest.json")
    )
    lines += ["", f"Shared data ({data.name}: imports, merges): {shared:.0f} s."]
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", type=Path, nargs="+", help="one run per seed")
    parser.add_argument(
        "--data", type=Path, required=True, help="the runs' shared data (REAL_DATA)"
    )
    parser.add_argument("--sets", nargs="+", default=["drive", "objects_adapted", "objects_other"])
    parser.add_argument("--iou", type=float, default=0.5)
    parser.add_argument("--min-points", type=int, default=5)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    seeds = len(args.runs)
    lines = [
        f"KITTI R40, Car, moderate; mean ± std over {seeds} run(s): {', '.join(r.name for r in args.runs)}."
    ]
    for set_name in args.sets:
        title = SET_TITLES.get(set_name, set_name)
        lines += ["", f"## On {title} ({set_name})", ""] + ap_table(args.runs, set_name)
        lines += ["", "Paired by seed:", ""] + paired_table(args.runs, set_name)
        lines += ["", "DALI against its own control, paired by seed:", ""]
        lines += dali_pairs_table(args.runs, set_name)
        lines += [
            "",
            "Where AP@0.7 is lost (each error kind fixed alone; mean over the seeds):",
            "",
        ]
        lines += loss_table(args.runs, set_name)
        exact = exact_recall_section(args.runs, set_name, args.data)
        lines += ["", *exact] if exact else []
    lines += ["", "## Paired bootstrap over the frames (`dali compare`, per seed)", ""]
    lines += bootstrap_table(args.runs, args.sets)
    lines += ["", "## Pseudo labels on the drive", ""]
    pseudo_lines, results = pseudo_section(args.runs, args.data, args.iou, args.min_points)
    lines += pseudo_lines
    lines += ["", "## Wall time per stage (s)", ""] + wall_times(args.runs, args.data)
    text = "\n".join(lines) + "\n"
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
        args.out.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
    print(text)


if __name__ == "__main__":
    main()
