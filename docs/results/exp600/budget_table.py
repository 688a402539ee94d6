"""Sessions 23/25: the rows of budget_job.sh (a 12,000-step budget), one line per seed and row.

    python docs/results/exp600/budget_table.py [--retrain-epochs 4] [--seeds 0]

Reads (from the directory holding runs/) each finished row's metrics on the 200 validation frames
(RUN/variants/budget-re<RE>/<row>/metrics.json, KITTI moderate from metrics_kitti.json) and on
the 800 fresh frames (runs/val800/experiment-s<SEED>/budget-re<RE>/<row>/metrics.json). Prints
AP_3D@0.7 (R40, front region, all boxes), AP_BEV@0.7 and AP_3D@0.7 at 50-80 m on the 800
frames and the mean predicted l, w, h; a row not finished is left blank or left out.
"""

import argparse
from pathlib import Path

from row_metrics import row_cells

# row: (eval dir on the 200 frames under the variant or the run, name on the 800 frames)
ROWS = {
    "control (source + test-time PTSN)": ("baselines/source_x2_budget/eval_ptsn", "control"),
    "sized control": ("baselines/source_x2_budget/eval_ptsn_sized", "control_sized"),
    "x1 long": ("x1_long/eval", "x1_long"),
    "oracle, x1 long's retraining length": (None, None),  # oracle_budget_job.sh's row
    "oracle, whole budget": ("baselines/oracle_x2_budget/eval", "oracle"),
}
HEADER = ("seed", "row", "steps", "AP_3D (200)", "KITTI mod 3D (200)", "AP_3D (800)", "BEV (800)",
          "3D 50-80 m (800)", "l, w, h (800)")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--retrain-epochs", type=int, default=4, help="the job's RETRAIN_EPOCHS")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    args = parser.parse_args()
    re = args.retrain_epochs
    steps = {  # 600 frames per epoch; pretraining 4 epochs, retraining 2 x RE epochs at 1:1
        "control (source + test-time PTSN)": (4 + 4 * re) * 600,
        "sized control": (4 + 4 * re) * 600,
        "x1 long": f"{4 * 600:,} + {4 * re * 600:,}",
        "oracle, x1 long's retraining length": 4 * re * 600,
        "oracle, whole budget": (4 + 4 * re) * 600,
    }
    print("| " + " | ".join(HEADER) + " |")
    print("|" + "---|" * len(HEADER))
    for seed in args.seeds:
        run = Path(f"runs/experiment-s{seed}")
        variant = run / "variants" / f"budget-re{re}"
        val800 = Path(f"runs/val800/experiment-s{seed}")
        for row, (eval_dir, name) in ROWS.items():
            if eval_dir is None:  # oracle_budget_job.sh's row: RUN/baselines/oracle_<E>ep
                eval_dir = f"../../baselines/oracle_{4 * re}ep/eval"
                big_dir = val800 / f"oracle_{4 * re}ep"
            else:
                big_dir = val800 / f"budget-re{re}" / name
            cells = row_cells(variant / eval_dir, big_dir)
            if cells is None:
                continue
            count = steps[row]
            cells.insert(0, f"{count:,}" if isinstance(count, int) else count)
            print(f"| {seed} | {row} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
