#!/bin/bash
# Session 23 (issue 18, item 3), seed 0 unless SEED: does a restarted learning-rate schedule waste
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
P="--protocol range --front-only --iou 0.7 --iou 0.5 --size-score-min 0.3"
$D retrain --init $R/baselines/oracle/model --source $R/data/target --ppcg $R/data/target \
    --source-size init --seed $SEED --epochs 4 --threads 1 --out $V/model
$D eval --model $V/model --data $R/data/target_val --scale 1.0 $P --workers 1 --no-progress \
    --out $V/eval
$D eval --pred $V/eval/predictions.parquet --gt $R/data/target_val --protocol kitti \
    --iou 0.7 --iou 0.5 --size-score-min 0.3 --out $V/eval/metrics_kitti.json
$D eval --model $V/model --data runs/val800/data-s$SEED --scale 1.0 $P --workers 1 --no-progress \
    --out runs/val800/experiment-s$SEED/oracle_restart
