#!/bin/bash
# a later run (the benchmark's target, item 3), seed 0 unless SEED: does a restarted learning-rate schedule waste
# the steps before it? The oracle on the pretraining budget (RUN/baselines/oracle: 2,400 steps on
# the labelled target frames, one one-cycle schedule) retrained for 4,800 more steps on the same
# frames with a fresh one-cycle schedule, as `retrain` runs after `pretrain` (`--source` and
# `--ppcg` both the labelled target frames, mix 1:1, 4 epochs). Reads target labels: a baseline,
# never a DALI stage. Against the oracle trained from scratch for 4,800 steps (oracle_budget_job.sh)
# and for 7,200 in one schedule (the x2-budget oracle). Evaluated at s = 1 on the 200 validation
# frames (range + KITTI) and on val800_job.sh's 800 fresh frames. Resumable.
#   bash docs/results/exp600/oracle_restart_job.sh            # from the directory holding runs/
set -euo pipefail
SEED=${SEED:-0}
D=${DALI:-.venv/bin/dali}
R=runs/experiment-s$SEED
V=$R/variants/oracle-restart
$D retrain --init $R/baselines/oracle/model --source $R/data/target --ppcg $R/data/target \
    --source-size init --seed $SEED --epochs 4 --threads 1 --out $V/model
source "$(dirname "$0")/eval_row.sh"
evaluate_row $V/model $V/eval runs/val800/experiment-s$SEED/oracle_restart --scale 1.0
