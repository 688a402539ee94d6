#!/bin/bash
# The equal-budget oracle (the 48 target frames with their labels, x2's 1,440 training frames) per
# seed, evaluated at scale 1 on the 400-frame validation set. Usage: oracle_job.sh (from a worktree
# with runs/)
set -e
cd "$(dirname "$0")/../../.."
for s in 0 1 2; do
  R=runs/d5-s$s; E=runs/val400-s$s/oracle
  make --no-print-directory $R/baselines/oracle_x2_budget/model/manifest.json RUN=$R SEED=$s FRAMES=48 VAL_FRAMES=48 TRAIN_FLAGS=--threads=1 EPOCHS=6 RETRAIN_EPOCHS=6
  .venv/bin/dali eval --model $R/baselines/oracle_x2_budget/model --data $R/data/target_val400 --scale 1.0 --protocol range --front-only --iou 0.7 --iou 0.5 --score-min 0.3 --workers 1 --no-progress --out $E
  [ -e $E/metrics_kitti.json ] || .venv/bin/dali eval --pred $E/predictions.parquet --gt $R/data/target_val400 --protocol kitti --iou 0.7 --iou 0.5 --score-min 0.3 --out $E/metrics_kitti.json > /dev/null
  echo "oracle $s done $(date)"
done
