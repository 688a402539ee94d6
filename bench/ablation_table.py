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
    """The table row of one eval directory (AP in %, sizes in m)."""
    metrics = json.loads((directory / "metrics.json").read_text())
    car = metrics["Car"]
    bands = " / ".join(f"{car['3d'][b]:.1f}" for b in ("0-30", "30-50", "50-80") if b in car["3d"])
    kitti_path = directory / "metrics_kitti.json"
    kitti = "—"
    if kitti_path.is_file():
        kitti = f"{json.loads(kitti_path.read_text())['Car']['3d']['moderate']:.1f}"
    sizes = "/".join(f"{v:.2f}" for v in metrics["sizes"]["pred"])
    scale = metrics.get("scale")
    scale_text = f"{scale:.3f}" if isinstance(scale, int | float) else "—"
    return (
        f"| {name} | {car['bev']['all']:.1f} | {car['3d']['all']:.1f} | {bands} | {kitti} "
        f"| {scale_text} | {sizes} |"
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
