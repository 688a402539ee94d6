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


def rows(re: int) -> list[tuple[str, str, str, str]]:
    """(row, eval dir on the 200 frames under RUN, dir on the 800 frames under
    runs/val800/experiment-s<SEED>, training steps) of budget_job.sh with RETRAIN_EPOCHS=re:
    600 frames per epoch, pretraining 4 epochs, retraining 2 x re epochs at 1:1."""
    variant, val800, whole = f"variants/budget-re{re}", f"budget-re{re}", (4 + 4 * re) * 600
    return [
        ("control (source + test-time PTSN)", f"{variant}/baselines/source_x2_budget/eval_ptsn",
         f"{val800}/control", f"{whole:,}"),
        ("sized control", f"{variant}/baselines/source_x2_budget/eval_ptsn_sized",
         f"{val800}/control_sized", f"{whole:,}"),
        ("x1 long", f"{variant}/x1_long/eval", f"{val800}/x1_long",
         f"{4 * 600:,} + {4 * re * 600:,}"),
        # oracle_budget_job.sh's row, EPOCHS=4 x re
        ("oracle, x1 long's retraining length", f"baselines/oracle_{4 * re}ep/eval",
         f"oracle_{4 * re}ep", f"{4 * re * 600:,}"),
        ("oracle, whole budget", f"{variant}/baselines/oracle_x2_budget/eval",
         f"{val800}/oracle", f"{whole:,}"),
    ]  # fmt: skip


HEADER = ("seed", "row", "steps", "AP_3D (200)", "KITTI mod 3D (200)", "AP_3D (800)", "BEV (800)",
          "3D 50-80 m (800)", "l, w, h (800)")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--retrain-epochs", type=int, default=4, help="the job's RETRAIN_EPOCHS")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    args = parser.parse_args()
    print("| " + " | ".join(HEADER) + " |")
    print("|" + "---|" * len(HEADER))
    for seed in args.seeds:
        run, val800 = Path(f"runs/experiment-s{seed}"), Path(f"runs/val800/experiment-s{seed}")
        for row, eval_dir, val800_dir, steps in rows(args.retrain_epochs):
            cells = row_cells(run / eval_dir, val800 / val800_dir)
            if cells is not None:
                print(f"| {seed} | {row} | {steps} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
