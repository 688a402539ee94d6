"""a later run: the rows of budget_job.sh (a 12,000-step budget) and of the jobs
on that budget (x2_long_job.sh; truth_job.sh with RETRAIN_EPOCHS; target_share_job.sh with
SET=rawtrue), one line per seed and row.

    python docs/results/exp600/budget_table.py [--retrain-epochs 4] [--seeds 0]

Reads (from the directory holding runs/) each finished row's metrics on the 200 validation frames
(RUN/variants/<job's variant>/<row>/metrics.json, KITTI moderate from metrics_kitti.json) and
on the 800 fresh frames (runs/val800/experiment-s<SEED>/<job's dir>/metrics.json). Prints
AP_3D@0.7 (R40, front region, all boxes), AP_BEV@0.7 and AP_3D@0.7 at 50-80 m on the 800
frames and the mean predicted l, w, h; a row not finished is left blank or left out.
"""

import argparse
from pathlib import Path

from row_metrics import row_cells


def target_share_rows(
    re: int,
    label: str,
    target_set: str,
    mix: str,
    steps: str,
    *,
    scratch: bool = False,
    at_s1: bool = False,
    variant: str = "",
) -> list[tuple[str, str, str, str]]:
    """The rows of `target_share_job.sh SET=target_set MIX=mix [INIT_FROM=scratch]
    [LABELS=variant | PPCG=variant]`
    on x1 long's 4 x re x 600 retraining steps (EPOCHS = 4 x re / (a + b) at MIX=a:b), named as
    the job names them; at_s1 adds its evaluation at s = 1 on the 800 frames (SET=rawtrue)."""
    source, target = (int(part) for part in mix.split(":"))
    epochs = 4 * re // (source + target)
    name = (
        f"x1long-{target_set}{f'-{variant}' if variant else ''}-mix{source}{target}"
        f"{'-scratch' if scratch else ''}{'' if epochs == 1 else f'-ep{epochs}'}"
    )
    rows = [(label, f"variants/{name}/eval", name, steps)]
    if at_s1:  # evaluated on the 800 frames only: no eval-s1 on the 200
        rows.append(("the same at s = 1", f"variants/{name}/eval-s1", f"{name}-s1", steps))
    return rows


def rows(re: int) -> list[tuple[str, str, str, str]]:
    """(row, eval dir on the 200 frames under RUN, dir on the 800 frames under
    runs/val800/experiment-s<SEED>, training steps) of the jobs with RETRAIN_EPOCHS=re: 600
    steps per pretraining epoch (4 epochs), 1,200 per retraining epoch (600 source + 600 PPCG
    frames), 2 x re retraining epochs; x2 splits them as make does (re // 2 in iteration 1)."""
    variant, val800, whole = f"variants/budget-re{re}", f"budget-re{re}", (4 + 4 * re) * 600
    x2_first = re // 2
    retrain = f"{4 * re * 600:,}"
    x1_long = f"{4 * 600:,} + {retrain}"
    return [
        ("control (source + test-time PTSN)", f"{variant}/baselines/source_x2_budget/eval_ptsn",
         f"{val800}/control", f"{whole:,}"),
        ("sized control", f"{variant}/baselines/source_x2_budget/eval_ptsn_sized",
         f"{val800}/control_sized", f"{whole:,}"),
        ("x1 long", f"{variant}/x1_long/eval", f"{val800}/x1_long", x1_long),
        ("x2 (make's split)", f"variants/x2long-re{re}/iter2/eval", f"x2long-re{re}/iter2",
         f"{4 * 600:,} + {x2_first * 1200:,} + {(2 * re - x2_first) * 1200:,}"),
        # truth_job.sh's variant: reads target labels, a diagnostic
        ("x1 long, PPCG from the true boxes (diagnostic)",
         f"variants/x1long-truth-matched-re{re}/x1_long/eval", f"x1long-truth-matched-re{re}",
         x1_long),
        # target_share_job.sh SET=rawtrue: reads target labels, diagnostics; 1:1 and
        # 1:7 with and without INIT_FROM=scratch
        *target_share_rows(re, "x1 long, raw target frames with all true labels (diagnostic), at its ŝ",
                           "rawtrue", "1:1", x1_long, at_s1=True),
        *target_share_rows(re, "x1 long, raw target, 1:7 (diagnostic), at its ŝ", "rawtrue",
                           "1:7", x1_long, at_s1=True),
        *target_share_rows(re, "raw target, 1:7, from scratch (diagnostic), at its ŝ", "rawtrue",
                           "1:7", retrain, scratch=True, at_s1=True),
        # SET=truth-matched|pseudo-matched at 1:7: truth_job.sh's PPCG frames
        # (MODE=truth-matched, pseudo-matched); diagnostics
        *target_share_rows(re, "x1 long, PPCG from the true boxes, 1:7 (diagnostic)",
                           "truth-matched", "1:7", x1_long),
        *target_share_rows(re, "x1 long, the found cars' pseudo boxes only (false ones dropped), "
                           "1:7 (diagnostic)", "pseudo-matched", "1:7", x1_long),
        # SET=ppcg: x1 long with less of the source on iteration 1's PPCG frames;
        # label-free, DALI variants
        *target_share_rows(re, "x1 long, PPCG 1:3", "ppcg", "1:3", x1_long),
        *target_share_rows(re, "x1 long, PPCG 1:7", "ppcg", "1:7", x1_long),
        # SET=rawpseudo: the same pseudo boxes on the raw target frames, no PPCG
        *target_share_rows(re, "x1 long, raw target frames with the pseudo boxes (no PPCG), 1:7",
                           "rawpseudo", "1:7", x1_long),
        # SET=ppcg LABELS=tta: PPCG from `pseudo-label --tta` boxes; label-free
        *target_share_rows(re, "x1 long, PPCG from --tta pseudo boxes, 1:7", "ppcg", "1:7", x1_long,
                           variant="tta"),
        # SET=ppcg PPCG=occ: `ppcg-rc/ppcg-cf --occlusion`; label-free
        *target_share_rows(re, "x1 long, PPCG with --occlusion, 1:7", "ppcg", "1:7", x1_long,
                           variant="occ"),
        *target_share_rows(re, "x1 long, PPCG with --occlusion (1:1)", "ppcg", "1:1", x1_long,
                           variant="occ"),
        # SET=ppcg LABELS=ground [PPCG=occ]: PPCG from `pseudo-label --fit-ground`
        # boxes, without and with --occlusion; label-free
        *target_share_rows(re, "x1 long, PPCG from --fit-ground boxes, 1:7", "ppcg", "1:7",
                           x1_long, variant="ground"),
        *target_share_rows(re, "x1 long, PPCG from --fit-ground boxes with --occlusion, 1:7",
                           "ppcg", "1:7", x1_long, variant="ground-occ"),
        # SET=ppcg LABELS=ignore: `pseudo-label --score-min 0.6 --ignore-min 0.3`,
        # `retrain --ignore-label DontCare` (the boxes scored 0.3-0.6 as ignore regions); label-free
        *target_share_rows(re, "x1 long, PPCG from boxes >= 0.6, 0.3-0.6 ignored, 1:7", "ppcg",
                           "1:7", x1_long, variant="ignore"),
        *target_share_rows(re, "x1 long, PPCG from boxes >= 0.6, 0.3-0.6 ignored (1:1)", "ppcg",
                           "1:1", x1_long, variant="ignore"),
        *target_share_rows(re, "x1 long, PPCG from boxes >= 0.6, no ignore regions, 1:7", "ppcg",
                           "1:7", x1_long, variant="cut06"),
        # oracle_budget_job.sh's row, EPOCHS=4 x re
        ("oracle, x1 long's retraining length", f"baselines/oracle_{4 * re}ep/eval",
         f"oracle_{4 * re}ep", retrain),
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
