#!/bin/bash
# a later run: the x2-budget oracle of a seed trained in bf16 (7,200 target frames, as
# RUN/baselines/oracle_x2_budget in fp32) and evaluated in bf16 on that seed's 800 fresh
# validation frames (runs/val800/data-s<SEED>, val800_job.sh): is the bf16 oracle's -1.9 of
# seed 0 a training draw? From the repository root, where the runs are; resumable (pretrain
# resumes from model.resume/, eval is skipped when up to date):
#   SEED=1 bash docs/results/exp600/bf16_oracle_job.sh
set -euo pipefail
SEED=${SEED:-1}
D=${DALI:-.venv/bin/dali}
O=runs/bf16-oracle-s$SEED
$D pretrain --source runs/experiment-s$SEED/data/target --seed $SEED --epochs 12 --precision bf16 --out $O/model
$D eval --precision bf16 --model $O/model --data runs/val800/data-s$SEED --scale 1.0 --protocol range \
  --front-only --iou 0.7 --iou 0.5 --size-score-min 0.3 --workers 1 --no-progress --out $O/eval_val800
