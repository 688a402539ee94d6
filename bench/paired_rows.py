"""Ablation rows paired by seed against a base row: per-seed AP and differences, mean ± sample std.

    python bench/paired_rows.py --seeds 0 1 2 --base "x1=runs/d5-s{seed}/iter1/eval" \\
        "x1, one long retraining=runs/d5long-s{seed}/iter1/eval" ...

Each NAME=PATTERN names an eval directory per seed ({seed} is replaced). Reads only what `dali
eval` wrote (metrics.json, metrics_kitti.json) with `dali report`'s readers; a seed whose row or
base is missing is left out of that row's differences (n says how many remain). For the rows
that `dali report` does not know (docs/RESULTS.md).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

METRICS = (("AP_3D@0.7", ("0.7", "3d")), ("AP_BEV@0.7", ("0.7", "bev")))
KITTI = "KITTI mod AP_3D@0.7"


def read_row(directory: Path) -> dict[str, float] | None:
    """{metric: AP %} of one eval directory, None when it has no metrics.json yet."""
    from dali_cli.reporting.report import read_kitti, read_metrics

    path = directory / "metrics.json"
    if not path.is_file():
        return None
    ap, _, _ = read_metrics(path, json.loads(path.read_text()))
    values = {title: ap.get(iou, {}).get(kind) for title, (iou, kind) in METRICS}
    moderate = read_kitti(directory / "metrics_kitti.json").get("0.7", {}).get("3d", {})
    values[KITTI] = moderate.get("moderate")
    return {k: float(v) for k, v in values.items() if v is not None}


def paired_table(base: tuple[str, str], rows: list[tuple[str, str]], seeds: list[int]) -> str:
    """Markdown: per row and metric, the per-seed values, the differences to the base and their
    mean ± sample std."""
    from dali_cli.reporting.columns import statistics

    lines = [
        f"| row | metric | per seed ({', '.join(map(str, seeds))}) | mean ± std "
        f"| minus {base[0]}, per seed | mean ± std |",
        "|---|---|---|---|---|---|",
    ]
    read = {  # every row's eval directories read once, the base's included
        pattern: {s: read_row(Path(pattern.format(seed=s))) for s in seeds}
        for _, pattern in [base, *rows]
    }
    base_values = read[base[1]]
    for name, pattern in [base, *rows]:
        values = read[pattern]
        for title in (*(t for t, _ in METRICS), KITTI):
            own = [values[s][title] for s in seeds if values[s] and title in values[s]]
            if not own:
                continue
            differences = [
                values[s][title] - base_values[s][title]
                for s in seeds
                if values[s] and base_values[s] and title in values[s] and title in base_values[s]
            ]
            mine, diff = statistics(own), statistics(differences)
            lines.append(
                f"| {name} | {title} | {' / '.join(f'{v:.1f}' for v in own)} | {cell(mine)} "
                f"| {' / '.join(f'{d:+.1f}' for d in differences) or '—'} | {cell(diff, '+')} |"
            )
    return "\n".join(lines)


def cell(stats: dict, sign: str = "") -> str:
    """mean ± std over the seeds and their count."""
    from dali_cli.reporting.columns import mean_std

    return "—" if stats["mean"] is None else f"{mean_std(stats, 1, sign)} (n = {stats['n']})"


def split(text: str) -> tuple[str, str]:
    name, _, pattern = text.partition("=")
    if not pattern:
        raise SystemExit(f"'{text}': give NAME=PATTERN (e.g. x1=runs/d5-s{{seed}}/iter1/eval)")
    return name, pattern


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", required=True)
    parser.add_argument("--base", required=True, help="NAME=PATTERN of the base row")
    parser.add_argument("rows", nargs="+", help="NAME=PATTERN of each row")
    args = parser.parse_args()
    print(paired_table(split(args.base), [split(r) for r in args.rows], args.seeds))


if __name__ == "__main__":
    main()
