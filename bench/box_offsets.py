"""Where do the boxes sit against the labels? The signed median offsets of true positives (along
the sensor's ray, across it, z, l, w, h; prediction - truth, metres) of several evaluations side
by side, per range band: what `dali eval`'s error breakdown prints for one, as one table.

    .venv/bin/python bench/box_offsets.py "PTSN only=RUN/eval_a" "tracked labels=RUN/eval_b" ...
        [--bands all 0-20 20-40] [--out offsets.md]

Each NAME=DIR is a `dali eval` output directory (its metrics.json's `errors` block: KITTI
moderate true positives at BEV IoU > 0.5). Prints a Markdown table, one row per evaluation and
band: the true positives counted, the share facing backwards and each field's median.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

FIELDS = ("radial_m", "tangential_m", "z_m", "l_m", "w_m", "h_m")


def offsets_of(metrics: dict, band: str) -> dict | None:
    """One band's line of an eval's metrics.json: count, flipped and each field's median, or
    None when the eval has no error breakdown or no true positive in that band."""
    errors = (metrics.get("errors") or {}).get("true_positives") or {}
    block = errors.get(band)
    if not block or not block.get("count"):
        return None
    return {
        "count": block["count"],
        "flipped": block.get("flipped", 0),
        **{field: block[field]["median"] for field in FIELDS if field in block},
    }


def table(rows: list[tuple[str, dict]], bands: list[str]) -> str:
    """The Markdown table of named metrics.json documents over `bands`."""
    lines = ["| evaluation | band | TPs | backwards | " + " | ".join(FIELDS) + " |",
             "|---|---|---|---|" + "---|" * len(FIELDS)]  # fmt: skip
    for name, metrics in rows:
        for band in bands:
            line = offsets_of(metrics, band)
            if line is None:
                lines.append(
                    f"| {name} | {band} | 0 | - | " + " | ".join("-" for _ in FIELDS) + " |"
                )
                continue
            cells = [f"{line[f]:+.3f}" if f in line else "-" for f in FIELDS]
            lines.append(f"| {name} | {band} | {line['count']} | "
                         f"{100 * line['flipped'] / line['count']:.1f} % | " + " | ".join(cells) + " |")  # fmt: skip
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("evals", nargs="+", metavar="NAME=DIR")
    parser.add_argument("--bands", nargs="+", default=["all", "0-20", "20-40"])
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    rows = []
    for pair in args.evals:
        name, _, directory = pair.partition("=")
        path = Path(directory) / "metrics.json"
        if not name or not path.is_file():
            parser.error(f"{pair}: expected NAME=DIR with DIR/metrics.json (a dali eval output)")
        rows.append((name, json.loads(path.read_text())))
    text = table(rows, args.bands)
    if args.out:
        args.out.write_text(text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
