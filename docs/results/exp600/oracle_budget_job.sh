#!/bin/bash
# a later run (the benchmark's target, item 3), seed 0 unless SEED: the oracle on x1 long's retraining budget.
# Target-only training from scratch with all true labels (reads target labels: a baseline, never
# a DALI stage), EPOCHS passes over the 600 target frames (default 8 = 4,800 steps, the steps x1
# long's retraining takes after its 2,400 pretraining steps), evaluated like the x2-budget oracle
# (s = 1) on the 200 validation frames (range + KITTI) and on val800_job.sh's 800 fresh frames.
# Against the oracle at 2,400 (the pretraining budget) and 7,200 steps (x2's): what labelled target
# training of the retraining's own length scores. Resumable (artifact directories).
#   SEED=1 bash docs/results/exp600/oracle_budget_job.sh     # from the directory holding runs/
set -euo pipefail
SEED=${SEED:-0}; EPOCHS=${EPOCHS:-8}
D=${DALI:-.venv/bin/dali}
R=runs/experiment-s$SEED
B=$R/baselines/oracle_${EPOCHS}ep
$D pretrain --source $R/data/target --seed $SEED --epochs $EPOCHS --threads 1 --out $B/model
source "$(dirname "$0")/eval_row.sh"
evaluate_row $B/model $B/eval runs/val800/experiment-s$SEED/oracle_${EPOCHS}ep --scale 1.0
