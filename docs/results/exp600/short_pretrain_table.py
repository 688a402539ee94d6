"""a later run: the rows of short_pretrain_job.sh, one line per seed and row.

    python docs/results/exp600/short_pretrain_table.py [--pre 2] [--seeds 0 1 2]

Reads (from the directory holding runs/) each finished row's metrics: the 200 validation frames
(RUN/variants/pretrain<PRE>/<row>/metrics.json, KITTI moderate from metrics_kitti.json where it
exists) and the 800 fresh frames (runs/val800/experiment-s<SEED>/pretrain<PRE>/<row>/). Prints
AP_3D@0.7 (R40, front region, all boxes), AP_BEV@0.7 and AP_3D@0.7 at 50-80 m on the 800
frames, the PTSN scale and the mean predicted l, w, h; a row not finished is left out.
"""

import argparse
import json
from pathlib import Path

from row_metrics import row_cells

ROWS = {  # row: (eval dir on the 200 frames, name on the 800, PTSN dir)
    "PTSN only": ("iter0/eval_ptsn", "iter0_ptsn", "iter1/ptsn"),
    "x1 long": ("x1_long/eval", "x1_long", "x1_long/ptsn"),
    "x2": ("iter2/eval", "x2", "iter3/ptsn"),
}


HEADER = ("seed", "row", "AP_3D (200)", "KITTI mod 3D (200)", "AP_3D (800)", "BEV (800)",
          "3D 50-80 m (800)", "ŝ", "l, w, h (800)")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pre", type=int, default=2, help="pretraining epochs of the variant")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args()
    print("| " + " | ".join(HEADER) + " |")
    print("|" + "---|" * len(HEADER))
    for seed in args.seeds:
        run = Path(f"runs/experiment-s{seed}/variants/pretrain{args.pre}")
        val800 = Path(f"runs/val800/experiment-s{seed}/pretrain{args.pre}")
        for row, (eval_dir, name, ptsn) in ROWS.items():
            cells = row_cells(run / eval_dir, val800 / name)
            if cells is None:
                continue
            scale = json.loads((run / ptsn / "manifest.json").read_text())["ptsn"]["scale"]
            cells.insert(-1, f"{scale:.3f}")  # before the sizes cell
            print(f"| {seed} | {row} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
