#!/bin/bash
# a later run (the benchmark's target, item 3), seed 0 unless SEED: x1 long with a longer retraining on the
# default pseudo labels. short_pretrain_job.sh moved 1,200 steps from pretraining to retraining
# (x1 long 6,000 retraining steps from a 1,200-step pseudo-labeller) and gained nothing; this
# separates the two changes: the default run's iteration 0 and iteration-1 PPCG frames (4
# pretraining epochs, 2,400 steps; rebuilt if absent, which also checks that this machine
# reproduces the recorded PTSN-only row), then x1 long retrained for RETRAIN epochs (default 5:
# 6,000 steps, 1,200 more than the default x1 long and than x2's budget allows) in
# RUN/variants/x1long-re$RETRAIN, evaluated on the 200 validation frames, KITTI's protocol and
# val800_job.sh's 800 fresh frames. One core (CORE, default 1), 1-thread training as the recorded
# runs. Resumable (make skips finished stages; training resumes from model.resume/).
#   bash docs/results/exp600/long_retrain_job.sh          # from the directory holding runs/
set -euo pipefail
SEED=${SEED:-0}; N=${RETRAIN:-5}; CORE=${CORE:-1}
HERE=$(cd "$(dirname "$0")" && pwd)
MAKEFILE=${MAKEFILE:-$HERE/../../../Makefile}
D=${DALI:-.venv/bin/dali}
R=runs/experiment-s$SEED
M=(taskset -c $CORE make -f "$MAKEFILE" SEED=$SEED SOURCE_SENSOR=waymo FRAMES=600 VAL_FRAMES=200 EPOCHS=4
   RETRAIN_EPOCHS=2 WORKERS=1 SYNTH_WORKERS=1 "TRAIN_FLAGS=--threads 1")
"${M[@]}" RUN=$R iter0 $R/iter1/rc/manifest.json $R/iter1/cf/manifest.json
source "$HERE/variant_links.sh"; ppcg_variant x1long-re$N
"${M[@]}" RUN=$V RETRAIN_EPOCHS_1=1 RETRAIN_EPOCHS_2=$(( N - 1 )) $V/x1_long/eval/manifest.json
source "$HERE/eval_row.sh"
kitti_row $V/x1_long/eval
D="taskset -c $CORE $D" val800_row $V/x1_long/model $O \
    --scale-from $V/x1_long/ptsn
