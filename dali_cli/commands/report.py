"""`dali report RUN`: the results table of a run (markdown + JSON) and its plots."""

from __future__ import annotations

import json
import os
from pathlib import Path

import click

from dali_cli.reporting.report import build_report
from dali_cli.store.atomic_file import write_text_atomically
from dali_cli.store.output_paths import REPORT_MARKER, check_report_dir


@click.command(name="report")
@click.argument("runs", nargs=-1, required=True,
                type=click.Path(exists=True, file_okay=False, path_type=Path))  # fmt: skip
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Where to write report.md / report.json / plots (default: RUN/report).")  # fmt: skip
@click.option("--plots/--no-plots", default=True, show_default=True, help="Draw PNG plots.")
def command(runs: tuple[Path, ...], out_dir: Path | None, plots: bool) -> None:
    """Summarize a run: AP_BEV / AP_3D at IoU 0.7 and 0.5 per method row (source only, SN, ROS,
    PTSN, PTSN + RC, PTSN + CF, x1, x2, x2 + ST, oracle, equal-budget controls), KITTI
    difficulties where metrics_kitti.json exist, sizes, PTSN scales and time per stage.

    Reads RUN/iter*/ and RUN/baselines/*/ artifacts; rows that were not run show "—".
    Writes RUN/report/report.md, report.json and plots/*.png, and prints the markdown.

    With several RUNs (e.g. one per seed), or a directory holding runs: mean ± sample std per
    row and column over the runs, written to --out (default: their common parent's report/).
    """
    from dali_cli.reporting.aggregate import aggregate_runs, find_runs, is_run

    if len(runs) > 1 or not is_run(runs[0]):
        found = find_runs(list(runs))
        if not found:
            raise click.ClickException(
                f"{', '.join(map(str, runs))}: no run artifacts (iter*/<stage>/manifest.json, "
                "*/eval/metrics.json): is it a RUN directory of the Makefile (make iter1 RUN=...)?"
            )
        out_dir = out_dir or Path(os.path.commonpath([r.resolve() for r in found])) / "report"
        out_dir = check_report_dir(out_dir)
        text, document = aggregate_runs(found)
        write_report(out_dir, text, document)
        return
    run = runs[0]
    out_dir = check_report_dir(out_dir or run / "report")
    text, document = build_report(run)
    out_dir.mkdir(parents=True, exist_ok=True)
    if plots:
        from dali_cli.reporting.plots import draw_plots

        document["plots"] = [str(p) for p in draw_plots(run, out_dir / "plots")]
        if not document["plots"]:
            click.echo(
                "no plots drawn (matplotlib missing, or no PTSN/PPCG artifacts yet)", err=True
            )
    write_report(out_dir, text, document)


def write_report(out_dir: Path, text: str, document: dict) -> None:
    """report.md and report.json into `out_dir` (each written atomically); print the markdown."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, content in (
        ("report.md", text),
        (
            "report.json",
            json.dumps({REPORT_MARKER: "dali report", **document}, indent=2, default=str),
        ),
    ):
        write_text_atomically(out_dir / name, content)
    click.echo(text)
    click.echo(f"report written to {out_dir}")
