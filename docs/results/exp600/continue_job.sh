#!/bin/bash
# Session 23 (issue 18), seed 0 unless SEED: x1 long with ONE learning-rate schedule across
# pretraining and retraining. Session 23 found that a restarted one-cycle schedule loses the steps
# before it (the oracle pretrained 2,400 steps and retrained 4,800 with a fresh schedule: 86.10,
# level with 4,800 steps from scratch, 2.0 below one 7,200-step schedule). Here the pretraining
# trains the first 4 epochs (2,400 steps) of a schedule spanning x2's 12-epoch budget (`pretrain
# --schedule-epochs 12`), the seed's usual chain pseudo-labels the target with that model (its
# sweep, pseudo labels, RC, CF), and x1 long's retraining (4,800 steps, 1:1) runs the rest of the
# same schedule (`retrain --continue-schedule`). Label-free: a DALI variant, same budget as the
# control. Rows: V/x1_long/eval (200 frames) and runs/val800/experiment-s$SEED/x1long-continued.
# Resumable (make skips finished stages; training resumes from model.resume/).
#   bash docs/results/exp600/continue_job.sh       # from the directory holding runs/
set -euo pipefail
SEED=${SEED:-0}
HERE=$(cd "$(dirname "$0")" && pwd)
MAKEFILE=${MAKEFILE:-$HERE/../../../Makefile}
D=${DALI:-.venv/bin/dali}
R=runs/experiment-s$SEED
V=$R/variants/x1long-continued
mkdir -p $V
for shared in data library; do ln -sfn ../../$shared $V/$shared; done
$D pretrain --source $V/data/source --seed $SEED --epochs 4 --schedule-epochs 12 --threads 1 \
    --out $V/iter0/model
make -f "$MAKEFILE" x1-long RUN=$V SEED=$SEED SOURCE_SENSOR=waymo FRAMES=600 VAL_FRAMES=200 \
    EPOCHS=4 RETRAIN_EPOCHS=2 "TRAIN_FLAGS=--threads 1 --continue-schedule" WORKERS=1
$D eval --model $V/x1_long/model --data runs/val800/data-s$SEED --scale-from $V/x1_long/ptsn \
    --protocol range --front-only --iou 0.7 --iou 0.5 --size-score-min 0.3 --workers 1 \
    --no-progress --out runs/val800/experiment-s$SEED/x1long-continued
