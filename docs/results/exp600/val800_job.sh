#!/bin/bash
# a later run: the main rows of the 600-frame runs re-evaluated on 800 fresh validation frames per
# seed (synthesized like RUN/data/target_val but with seed SEED + 5000; 4x the 200 frames the
# runs were measured on, so the frames' share of a one-seed difference halves), each model at its
# own PTSN scale as in the Makefile; the sized control from the control's predictions; then a
# paired bootstrap (dali compare) of every row against the x2-budget control, R40 and R400:
# runs/val800/RUN/compare_r{40,400}.json. From the repository root (resumable: every eval is an
# artifact directory, skipped when up to date):
#   bash docs/results/exp600/val800_job.sh                    # all runs below that are finished
#   RUNS="experiment-s0" bash docs/results/exp600/val800_job.sh
#   EVAL_FLAGS="--precision bf16" RUNS=...   # options of every model eval
set -uo pipefail
D=${DALI:-.venv/bin/dali}
X=${EVAL_FLAGS:-}
P="--protocol range --front-only --iou 0.7 --iou 0.5 --size-score-min 0.3"
for run in ${RUNS:-experiment-s0 experiment-s1 experiment-s2 experiment-nuscenes-s0 experiment-nuscenes-s1 experiment-nuscenes-s2}; do
  R=runs/$run; O=runs/val800/$run
  [ -f $R/baselines/oracle_x2_budget/eval/manifest.json ] || { echo "$run: not finished"; continue; }
  seed=$(python3 -c "import json; print(json.load(open('$R/data/target_val/manifest.json'))['seed'] - 2000)")
  V=runs/val800/data-s$seed  # the target is KITTI-like in both tasks: one set per seed
  [ -f $V/manifest.json ] || $D synth --sensor kitti --cars kitti --frames 800 --seed $((seed + 5000)) \
    --executor local --workers 1 --out $V || exit 1
  B=$R/baselines
  declare -A ROWS=(  # row -> "model scale-option"
    [control]="$B/source_x2_budget/model --scale-from $B/source_x2_budget/ptsn"
    [x2]="$R/iter2/model --scale-from $R/iter3/ptsn"
    [x1_long]="$R/x1_long/model --scale-from $R/x1_long/ptsn"
    [oracle]="$B/oracle_x2_budget/model --scale 1.0"
  )
  for row in control x2 x1_long oracle; do
    set -- ${ROWS[$row]}
    $D eval $X --model $1 --data $V $2 $3 $P --workers 1 --no-progress --out $O/$row || exit 1
  done
  $D eval --pred $O/control/predictions.parquet --gt $V --scale-from $B/source_x2_budget/ptsn \
    --size-correction per-dim $P --out $O/control_sized || exit 1
  for pos in 40 400; do
    $D compare --gt $V --pred control=$O/control/predictions.parquet --pred x2=$O/x2/predictions.parquet \
      --pred "x1 long"=$O/x1_long/predictions.parquet --pred "sized control"=$O/control_sized/predictions.parquet \
      --pred oracle=$O/oracle/predictions.parquet --protocol range --front-only --iou 0.7 \
      --recall-positions $pos --samples 400 --seed 0 --no-progress --out $O/compare_r$pos.json || exit 1
  done
done
