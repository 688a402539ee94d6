#!/bin/bash
# a later run: a paired bootstrap over the validation frames (dali compare) of the main rows against
# the x2-budget control (and the x2-budget oracle, for the gap), per run:
# RUN/compare_x2_budget_r40.json (POSITIONS=400: the fine recall grid, _r400). From the repository root:
#   bash docs/results/exp600/compare_job.sh; POSITIONS=400 bash docs/results/exp600/compare_job.sh
#   (RUNS="experiment-s0 ..." for some runs only)
set -uo pipefail
for run in ${RUNS:-experiment-s0 experiment-s1 experiment-s2 experiment-nuscenes-s0 experiment-nuscenes-s1}; do
  R=runs/$run
  [ -f $R/baselines/oracle_x2_budget/eval/predictions.parquet ] || { echo "$run: not finished"; continue; }
  ${DALI:-.venv/bin/dali} compare --gt $R/data/target_val \
    --pred control=$R/baselines/source_x2_budget/eval_ptsn/predictions.parquet \
    --pred x2=$R/iter2/eval/predictions.parquet \
    --pred "x1 long"=$R/x1_long/eval/predictions.parquet \
    --pred "sized control"=$R/baselines/source_x2_budget/eval_ptsn_sized/predictions.parquet \
    --pred oracle=$R/baselines/oracle_x2_budget/eval/predictions.parquet \
    --protocol range --front-only --iou 0.7 --recall-positions "${POSITIONS:-40}" --samples 400 --seed 0 --no-progress \
    --out $R/compare_x2_budget_r${POSITIONS:-40}.json
done
