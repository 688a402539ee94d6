"""Session 24: the rows of short_pretrain_job.sh, one line per seed and row.

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

ROWS = {  # row: (eval dir on the 200 frames, name on the 800, PTSN dir)
    "PTSN only": ("iter0/eval_ptsn", "iter0_ptsn", "iter1/ptsn"),
    "x1 long": ("x1_long/eval", "x1_long", "x1_long/ptsn"),
    "x2": ("iter2/eval", "x2", "iter3/ptsn"),
}


HEADER = ("seed", "row", "AP_3D (200)", "KITTI mod 3D (200)", "AP_3D (800)", "BEV (800)",
          "3D 50-80 m (800)", "ŝ", "l, w, h (800)")  # fmt: skip


def metrics(path: Path) -> dict | None:
    """A metrics.json, None when the row has not finished."""
    return json.loads(path.read_text()) if path.is_file() else None


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
            small_metrics = metrics(run / eval_dir / "metrics.json")
            big_metrics = metrics(val800 / name / "metrics.json")
            if small_metrics is None and big_metrics is None:
                continue
            small = small_metrics["Car"] if small_metrics else None
            big = big_metrics["Car"] if big_metrics else None
            kitti_metrics = metrics(run / eval_dir / "metrics_kitti.json")
            kitti = kitti_metrics["Car"]["3d"]["moderate"] if kitti_metrics else None
            scale = json.loads((run / ptsn / "manifest.json").read_text())["ptsn"]["scale"]
            sizes = big_metrics["sizes"]["pred"] if big_metrics else None
            cells = [
                f"{small['3d']['all']:.2f}" if small else "",
                f"{kitti:.2f}" if kitti is not None else "",
                f"{big['3d']['all']:.2f}" if big else "",
                f"{big['bev']['all']:.2f}" if big else "",
                f"{big['3d']['50-80']:.2f}" if big else "",
                f"{scale:.3f}",
                ", ".join(f"{v:.2f}" for v in sizes) if sizes else "",
            ]
            print(f"| {seed} | {row} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
