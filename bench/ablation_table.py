"""One Markdown row per evaluation directory: AP_BEV / AP_3D @0.7 of the front-region all-box
protocol, the range bands, KITTI moderate AP_3D@0.7 (when metrics_kitti.json is there), ŝ and the
mean predicted l / w / h. For ablation rows that `dali report` does not know (docs/RESULTS.md).

    python bench/ablation_table.py NAME=RUN/ablations/x/eval [NAME=DIR ...]

Reads only what `dali eval` wrote (metrics.json, metrics_kitti.json); computes nothing new.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

HEADER = (
    "| row | AP_BEV@0.7 | AP_3D@0.7 | 3D 0-30 / 30-50 / 50-80 m | KITTI mod 3D@0.7 | ŝ "
    "| pred l/w/h (m) |\n|---|---|---|---|---|---|---|"
)


def row(name: str, directory: Path) -> str:
    """The table row of one eval directory (AP in %, sizes in m), read with `dali report`'s own
    readers of metrics.json and metrics_kitti.json."""
    from dali_cli.reporting.report import BANDS, read_bands, read_kitti, read_metrics

    path = directory / "metrics.json"
    document = json.loads(path.read_text())
    ap, sizes, scale = read_metrics(path, document)
    bands = read_bands(document)
    band_text = " / ".join(f"{bands[b]['3d']:.1f}" for b in BANDS if b in bands)
    moderate = read_kitti(directory / "metrics_kitti.json").get("0.7", {}).get("3d", {})
    kitti = "—" if moderate.get("moderate") is None else f"{moderate['moderate']:.1f}"
    size_text = "/".join(f"{v:.2f}" for v in sizes["pred"])
    scale_text = f"{scale:.3f}" if isinstance(scale, int | float) else "—"
    return (
        f"| {name} | {ap['0.7']['bev']:.1f} | {ap['0.7']['3d']:.1f} | {band_text} | {kitti} "
        f"| {scale_text} | {size_text} |"
    )


def main(arguments: list[str]) -> int:
    if not arguments:
        print(__doc__, file=sys.stderr)
        return 2
    print(HEADER)
    for argument in arguments:
        name, _, path = argument.rpartition("=")
        directory = Path(path)
        if not (directory / "metrics.json").is_file():
            print(f"{directory}: no metrics.json (not a dali eval directory)", file=sys.stderr)
            return 1
        print(row(name or directory.parent.name, directory))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
