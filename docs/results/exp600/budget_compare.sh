#!/bin/bash
# Sessions 25/26 (issue 18), seed 0 unless SEED: the paired bootstrap (`dali compare`, 400 draws,
# R40 and R400) of the 12,000-step rows on the 800 fresh frames, against the control: x1 long and
# the control's rows of budget_job.sh, x2 of x2_long_job.sh, and the diagnostics that read target
# labels, PPCG from the true boxes (truth_job.sh RETRAIN_EPOCHS=4) and the raw target frames with
# all true labels at its ŝ and at s = 1 (target_share_job.sh SET=rawtrue MIX=1:1 EPOCHS=8), each
# where finished.
# Writes runs/val800/experiment-s$SEED/budget-re$RE/compare26_r{40,400}.json.
#   taskset -c 0 bash docs/results/exp600/budget_compare.sh     # from the directory holding runs/
set -euo pipefail
SEED=${SEED:-0}; RE=${RETRAIN_EPOCHS:-4}; D=${DALI:-.venv/bin/dali}
O=runs/val800/experiment-s$SEED
rows=()  # NAME=DIR under O; NAME holds no '='
for row in "control=budget-re$RE/control" "x1 long=budget-re$RE/x1_long" "x2=x2long-re$RE/iter2" \
    "x1 long, true boxes=x1long-truth-matched-re$RE" "x1 long, raw target=x1long-rawtrue-mix11-ep$(( 2 * RE ))" \
    "x1 long, raw target at s 1=x1long-rawtrue-mix11-ep$(( 2 * RE ))-s1" \
    "oracle=budget-re$RE/oracle"; do
  [ -f "$O/${row#*=}/predictions.parquet" ] && rows+=(--pred "${row%%=*}=$O/${row#*=}/predictions.parquet")
done
for positions in 40 400; do
  $D compare "${rows[@]}" --gt runs/val800/data-s$SEED --protocol range --front-only --iou 0.7 \
      --recall-positions $positions --samples 400 --seed 0 --no-progress \
      --out $O/budget-re$RE/compare26_r$positions.json
done
