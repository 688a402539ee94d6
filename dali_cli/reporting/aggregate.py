"""Mean ± standard deviation of the results of several runs (one per seed) of the same benchmark:
`dali report RUN1 RUN2 ...` or `dali report PARENT` (every RUN directory below it).

Each run is first summarized by `report.build_report`; a figure enters a row's mean only from the
runs that have it, and the table says how many did (n). The standard deviation is the sample one
(ddof = 1), undefined ("—") for a single run.
"""

from __future__ import annotations

from pathlib import Path

from dali_cli.reporting import compare as report_compare
from dali_cli.reporting import paired as report_paired
from dali_cli.reporting.columns import COLUMNS, dig, mean_std, statistics
from dali_cli.reporting.report import BANDS, DIFFICULTIES, build_report

SCALARS = (
    "gap_closed_3d_0.7",
    "gap_closed_bev_0.7",
    "gap_closed_equal_budget_3d_0.7",
    "gap_closed_equal_budget_bev_0.7",
    "gap_closed_equal_budget_x1_long_3d_0.7",
    "gap_closed_sized_control_3d_0.7",
    "gap_closed_sized_control_x1_long_3d_0.7",
)
TABLE_COLUMNS = ("BEV@0.7", "3D@0.7", "KITTI 3D@0.7 moderate", "pred l", "pred w", "pred h")


def is_run(path: Path) -> bool:
    """Whether `path` holds a Makefile run's artifacts (iter*/ or baselines/ with outputs)."""
    patterns = ("iter*/*/manifest.json", "iter*/*/metrics.json", "baselines/*/*/*.json")
    return path.is_dir() and any(next(path.glob(p), None) for p in patterns)


def find_runs(paths: list[Path]) -> list[Path]:
    """The runs named: each path that is a run, else the runs directly below it (sorted)."""
    runs = []
    for path in paths:
        runs += [path] if is_run(path) else sorted(p for p in path.iterdir() if is_run(p))
    return runs


def aggregate_documents(documents: list[dict], section: str = "target") -> list[dict]:
    """Per row name of `section` ("target", "source" or "controls"), statistics per column."""
    names: list[str] = []
    for document in documents:
        names += [r["name"] for r in document.get(section, []) if r["name"] not in names]
    rows = []
    for name in names:
        found = [r for d in documents for r in d.get(section, []) if r["name"] == name]
        columns = {}
        for title, keys in COLUMNS:
            values = [v for v in (dig(r, keys) for r in found) if v is not None]
            columns[title] = statistics(values)
        rows.append({"name": name, "columns": columns})
    return rows


def markdown(rows: list[dict], columns=TABLE_COLUMNS) -> str:
    lines = ["| method | n | " + " | ".join(columns) + " |", "|---|---|" + "---|" * len(columns)]
    for row in rows:
        n = max(row["columns"][c]["n"] for c in columns)
        if n == 0:
            continue
        cells = [mean_std(row["columns"][c], 3 if c.startswith("pred") else 2) for c in columns]
        lines.append(f"| {row['name']} | {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def aggregate_runs(runs: list[Path]) -> tuple[str, dict]:
    """Markdown and a JSON-ready dict: mean ± std over `runs` of every row and gap figure, and
    the paired differences of the DALI rows against their equal-budget controls."""
    documents = [build_report(run)[1] for run in runs]
    paired = report_paired.paired_differences(documents, [str(r) for r in runs])
    target = aggregate_documents(documents, "target") + aggregate_documents(documents, "controls")
    source = aggregate_documents(documents, "source")
    scalars = {
        key: statistics([d[key] for d in documents if isinstance(d.get(key), int | float)])
        for key in SCALARS
    }
    parts = [
        f"# dali report: mean ± std over {len(runs)} runs",
        "",
        "Runs: " + ", ".join(str(r) for r in runs),
        "",
        "## Target validation (Car AP_R40, %; front region, all boxes, and KITTI moderate)",
        "",
        markdown(target),
        "",
        "### KITTI difficulties (AP_3D@0.7)",
        "",
        markdown(target, tuple(f"KITTI 3D@0.7 {d}" for d in DIFFICULTIES)),
    ]
    by_band = tuple(f"3D@0.7 {band} m" for band in BANDS)
    if any(row["columns"][column]["n"] for row in target for column in by_band):
        parts += ["", "### By distance (AP_3D@0.7, front region)", "", markdown(target, by_band)]
    if any(row["columns"]["3D@0.7"]["n"] for row in source):
        parts += ["", "## Source validation", "", markdown(source, ("BEV@0.7", "3D@0.7"))]
    parts += ["", "## Gap closed (share, mean ± std over runs)", ""]
    for key, stats in scalars.items():
        parts.append(f"- {key}: {mean_std(stats, 3)} (n = {stats['n']})")
    if paired:
        parts += [
            "",
            "## DALI against its equal-budget control, paired by run (AP points)",
            "",
            report_paired.markdown(paired),
        ]
    compare_parts, compared = report_compare.sections(runs)
    parts += compare_parts
    document = {
        "runs": [str(r) for r in runs],
        "target": target,
        "source": source,
        "scalars": scalars,
        "paired": paired,
        "compare": compared,
        "std": "sample standard deviation (ddof = 1) over runs",
    }
    return "\n".join(parts) + "\n", document
