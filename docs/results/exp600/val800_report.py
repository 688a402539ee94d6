"""Aggregate val800_job.sh's compare files: per task, each run's Δ to the x2-budget
control ± the frames' std, and mean ± std over the runs, R400 and R40, as `dali report` does for
RUN/compare_r*.json. From the repository root:
    python docs/results/exp600/val800_report.py runs/val800 > docs/results/exp600/val800.md
"""

import sys
from pathlib import Path

from dali_cli.reporting import compare as report_compare

root = Path(sys.argv[1] if len(sys.argv) > 1 else "runs/val800")
for task, pattern in (("Waymo-like → KITTI-like", "experiment-s*"),
                      ("nuScenes-like → KITTI-like", "experiment-nuscenes-s*")):  # fmt: skip
    runs = sorted(p for p in root.glob(pattern) if (p / "compare_r40.json").is_file())
    if not runs:
        continue
    parts, _ = report_compare.sections(runs)
    print(f"# {task}: {', '.join(p.name for p in runs)}, 800 validation frames per seed")
    print("\n".join(parts).replace("## ", "### "))
    print()
