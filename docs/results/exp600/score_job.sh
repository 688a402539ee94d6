#!/bin/bash
# x1 long or x2 with a higher pseudo-label score cut (the benchmark's target, a later run: at 600 frames 858 of
# iteration 1's 4,960 pseudo boxes lie >= 2 m from any car, score median 0.46 against 0.76 for
# the true ones; bench/pseudo_labels.py). The Makefile's own chain in a variant RUN that links
# the seed's data, library, pretrained model and first sweep; only pseudo-label gets
# `--score-min SCORE` (PSEUDO_FLAGS; the later option wins), the sweeps and evaluations keep 0.3.
#   SCORE=0.5 ROW=x1long bash docs/results/exp600/score_job.sh      # from the repository root
#   SCORE=0.5 ROW=x2 SEED=1 bash docs/results/exp600/score_job.sh   # resumable like any make run
# Rows: V/x1_long/eval (ROW=x1long); V/iter1/eval (x1) and V/iter2/eval (x2) (ROW=x2).
#
set -euo pipefail
SEED=${SEED:-0}; SCORE=${SCORE:-0.5}; ROW=${ROW:-x1long}
R=runs/experiment-s$SEED
V=$R/variants/$ROW-score${SCORE/./}
source "$(dirname "$0")/variant_links.sh"; link_variant $V ptsn
goal=$([ "$ROW" = x2 ] && echo iter2 || echo x1-long)
make $goal kitti-protocol RUN=$V SEED=$SEED SOURCE_SENSOR=waymo FRAMES=600 VAL_FRAMES=200 EPOCHS=4 \
    RETRAIN_EPOCHS=2 PSEUDO_FLAGS="--score-min $SCORE" TRAIN_FLAGS="--threads 1"
