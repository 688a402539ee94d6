"""Every row of two runs of the same seed side by side:
AP_3D / AP_BEV @0.7 (front region, all boxes), KITTI moderate AP_3D@0.7, the PTSN scale and the
mean predicted size, from each run's `dali report` (RUN/report/report.json).

    python docs/results/exp600/precision_pairs.py RUN_A RUN_B [--names fp32 bf16]

Prints a markdown table, then each run's DALI rows minus its x2-budget control."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

CONTROL = "baselines/source_x2_budget/eval_ptsn/metrics.json"
PAIRED = {"x2": "iter2/eval/metrics.json", "x1 long": "x1_long/eval/metrics.json",
          "x1": "iter1/eval/metrics.json",
          "oracle (x2's budget)": "baselines/oracle_x2_budget/eval/metrics.json"}  # fmt: skip


def rows(run: Path) -> dict[tuple[str, str], dict]:
    """(section, metrics path) -> report row, for the target and control sections."""
    report = json.loads((run / "report" / "report.json").read_text())
    return {  # rows the run did not produce are listed without figures: left out
        (s, r["path"]): r
        for s in ("target", "controls", "source")
        for r in report[s]
        if r.get("ap")
    }


def ap3d(row: dict) -> float:
    return row["ap"]["0.7"]["3d"]


def cell(row: dict | None) -> list[str]:
    if row is None:
        return ["–"] * 4
    return [
        f"{ap3d(row):.2f}",
        f"{row['ap']['0.7']['bev']:.2f}",
        f"{row['kitti']['0.7']['3d']['moderate']:.2f}" if row.get("kitti") else "–",
        f"{row['scale']:.3f}" if row.get("scale") else "–",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("runs", type=Path, nargs=2)
    parser.add_argument("--names", nargs=2, default=["fp32", "bf16"])
    args = parser.parse_args()
    a, b = (rows(run) for run in args.runs)
    na, nb = args.names
    print(f"| section | row | AP_3D {na} | {nb} | Δ | AP_BEV {na} | {nb} | KITTI mod {na} | {nb} "
          f"| ŝ {na} | {nb} | l/w/h {na} | {nb} |")  # fmt: skip
    print("|" + "---|" * 13)
    for key in list(a) + [k for k in b if k not in a]:
        ra, rb = a.get(key), b.get(key)
        name = (ra or rb)["name"]
        ca, cb = cell(ra), cell(rb)
        delta = f"{ap3d(rb) - ap3d(ra):+.2f}" if ra and rb else "–"
        sizes = ["/".join(f"{v:.2f}" for v in r["sizes"]["pred"]) if r else "–" for r in (ra, rb)]
        print(f"| {key[0]} | {name} | {ca[0]} | {cb[0]} | {delta} | {ca[1]} | {cb[1]} | {ca[2]} "
              f"| {cb[2]} | {ca[3]} | {cb[3]} | {sizes[0]} | {sizes[1]} |")  # fmt: skip
    print()
    print(f"| row − x2-budget control (AP_3D@0.7) | {na} | {nb} |")
    print("|---|---|---|")
    for label, path in PAIRED.items():
        values = []
        for table in (a, b):
            row, control = (
                table.get(("target", path)) or table.get(("controls", path)),
                table.get(("controls", CONTROL)),
            )
            values.append(f"{ap3d(row) - ap3d(control):+.2f}" if row and control else "–")
        print(f"| {label} | {values[0]} | {values[1]} |")


if __name__ == "__main__":
    main()
