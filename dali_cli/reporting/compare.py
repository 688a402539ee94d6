"""The `dali compare` files of several runs, aggregated for `dali report RUN1 RUN2 ...`.

`make compare` (a goal of `make experiment`) writes RUN/compare_r400.json and RUN/compare_r40.json:
the main rows against the x2-budget control on the same validation frames, with a paired
bootstrap over the frames (`dali_cli.evaluation.bootstrap`). Per row this module gives each run's difference
Δ to the reference row (AP points, on all frames) with the std of Δ over that run's draws (the
frames' share of the chance), and the mean ± sample std of Δ over the runs (the seeds' share).
R400 (the fine recall grid) has no R40 steps: the figure to read when differences are small
(docs/evaluation.md, "How finely AP resolves a difference").
"""

from __future__ import annotations

from pathlib import Path

from dali_cli.reporting.columns import statistics
from dali_cli.runtime.errors import StageError
from dali_cli.store.regular_files import read_json_file

FILES = (("compare_r400.json", "R400, the fine recall grid"), ("compare_r40.json", "R40"))
METRIC = "3d all"  # AP_3D@0.7 of the front region, all boxes (make compare's settings)


def read_summary(path: Path) -> dict | None:
    """The "bootstrap" block of one `dali compare` file (None when absent or not one)."""
    try:
        document = read_json_file(path, "comparison file")
    except (OSError, ValueError, StageError):
        return None
    summary = document.get("bootstrap") if isinstance(document, dict) else None
    return summary if isinstance(summary, dict) and "rows" in summary else None


def compare_differences(runs: list[Path], name: str, metric: str = METRIC) -> list[dict]:
    """Per row after the reference, in the order of the first file: per run {"run", "delta",
    "delta_std", "share"} and the statistics of the deltas over the runs that have the row."""
    summaries = [(str(run), read_summary(Path(run) / name)) for run in runs]
    summaries = [(run, s) for run, s in summaries if s is not None]
    if not summaries:
        return []
    rows = [n for n in summaries[0][1]["rows"] if n != summaries[0][1].get("reference")]
    results = []
    for row in rows:
        per_run = []
        for run, summary in summaries:
            entry = summary["rows"].get(row, {}).get(metric, {})
            if entry.get("delta") is not None:
                per_run.append({
                    "run": run, "delta": entry["delta"], "delta_std": entry.get("delta_std"),
                    "share": entry.get("share_not_above_reference"),
                    "reference": summary.get("reference"),
                })  # fmt: skip
        stats = statistics([p["delta"] for p in per_run])
        results.append({"row": row, **stats, "per_run": per_run})
    return results


def markdown(results: list[dict], grid: str) -> str:
    """A table: row, n, per run Δ ± the frames' std, mean ± std over runs."""
    reference = next((p["reference"] for r in results for p in r["per_run"]), "the first row")
    lines = [
        f"AP_3D@0.7 ({grid}), each row minus {reference} on the same frames; per run ± the std "
        "of the difference over the bootstrap draws of the frames; then mean ± std over runs.",
        "",
        "| row | n | per run (Δ ± frames' std) | mean ± std over runs |",
        "|---|---|---|---|",
    ]
    for result in results:
        if not result["n"]:
            continue
        values = " / ".join(
            f"{p['delta']:+.2f}"
            + (f" ± {p['delta_std']:.2f}" if p["delta_std"] is not None else "")
            for p in result["per_run"]
        )
        spread = "—" if result["std"] is None else f"{result['std']:.2f}"
        lines.append(
            f"| {result['row']} | {result['n']} | {values} | {result['mean']:+.2f} ± {spread} |"
        )
    return "\n".join(lines)


def sections(runs: list[Path]) -> tuple[list[str], dict]:
    """Markdown lines (empty without compare files) and {file name: results} for report.json."""
    parts, document = [], {}
    for name, grid in FILES:
        results = compare_differences(runs, name)
        if not any(r["n"] for r in results):
            continue
        document[name] = results
        parts += ["", f"## Against the x2-budget control on the same frames (`dali compare`, {grid})",
                  "", markdown(results, grid)]  # fmt: skip
    return parts, document
