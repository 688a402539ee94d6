#!/bin/bash
# The 600-frame benchmark, seed 0, with the defaults of session 14 (issue 18; docs/RESULTS.md,
# session 15). What it runs is `make experiment SEEDS=0` with every goal; the rows come in this
# order (main rows first), two 1-thread training jobs at a time on a 2-core VM.
#   bash docs/results/exp600/job.sh        # from the repository root; resumable (make skips
#                                          # every stage whose manifest is up to date)
set -euo pipefail
V="RUN=runs/experiment-s0 SEED=0 SOURCE_SENSOR=waymo FRAMES=600 VAL_FRAMES=200 EPOCHS=4 RETRAIN_EPOCHS=2"
T='TRAIN_FLAGS=--threads 1'
# the main rows: x2 (make iter2), its equal-budget controls, x1 long
make -j2 iter2 controls-x2 $V "$T"
make x1-long $V "$T"
# seed 0 only (issue 18 allows it): x1's control, SN, ROS, oracle at the pretraining budget, RC
# only, CF only; then the forgetting check, KITTI easy/moderate/hard of every row, the report
make -j2 controls baselines cross-domain kitti-protocol $V "$T"
make experiment SEEDS=0 TRAIN_FLAGS="--threads 1"
