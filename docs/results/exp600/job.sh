#!/bin/bash
# The 600-frame benchmark, seed 0, with the defaults of a later run (the benchmark's target; docs/RESULTS.md,
# a later run). What it runs is `make experiment SEEDS=0` with every goal; the rows come in this
# order (main rows first), two 1-thread training jobs at a time on a 2-core VM.
#   bash docs/results/exp600/job.sh        # from the repository root; resumable (make skips
#                                          # every stage whose manifest is up to date)
#   SEED=1 bash docs/results/exp600/job.sh # another seed: its own data and RUN, main rows only
#   SOURCE_SENSOR=nuscenes bash docs/results/exp600/job.sh  # the nuScenes-like -> KITTI-like
#                                          # task (runs/experiment-nuscenes-s0): main rows, x1's
#                                          # control and x2 + ST (the paper's double dagger)
set -euo pipefail
SEED=${SEED:-0}
SOURCE_SENSOR=${SOURCE_SENSOR:-waymo}
RUN=runs/experiment$([ "$SOURCE_SENSOR" = waymo ] || echo "-$SOURCE_SENSOR")-s$SEED  # as make experiment
V="RUN=$RUN SEED=$SEED SOURCE_SENSOR=$SOURCE_SENSOR FRAMES=600 VAL_FRAMES=200 EPOCHS=4 RETRAIN_EPOCHS=2"
T='TRAIN_FLAGS=--threads 1'
# the main rows: x2's chain alone first (`make -j2` does not keep goal order: given `iter2
# controls-x2` it started both 7,200-frame controls and left the chain waiting), then x1 long and
# x2's equal-budget controls side by side
if [ "$SEED" != 0 ] || [ "$SOURCE_SENSOR" != waymo ]; then
    # the other seeds and the other task: main rows, forgetting and KITTI protocol only
    # x2's chain and the x2-budget control (which needs none of it) side by side, then x1 long
    # and the x2-budget oracle side by side
    make data $V "$T"  # first: both would synthesize it, and a FrameSet has one writer
    make iter2 $V "$T" & chain=$!
    make $RUN/baselines/source_x2_budget/eval_ptsn/manifest.json $V "$T"
    wait $chain
    make -j2 x1-long controls-x2 $V "$T"
    goals="iter2 x1-long controls-x2 cross-domain"
    if [ "$SOURCE_SENSOR" = nuscenes ]; then  # x1 paired with its control; ST is this task's step
        make -j2 controls-x1 iter2-st $V "$T"
        goals="$goals controls-x1 iter2-st"
    fi
    make cross-domain $RUN/x1_long/eval_source_sized/manifest.json $V "$T"
    make experiment SEEDS="$SEED" SOURCE_SENSOR="$SOURCE_SENSOR" \
        EXPERIMENT_GOALS="$goals" EXPERIMENT_FIRST_SEED_GOALS= TRAIN_FLAGS="--threads 1"
    exit 0
fi
make iter2 $V "$T"
make -j2 x1-long controls-x2 $V "$T"
# seed 0 only (the benchmark's target allows it): x1's control, SN, ROS, oracle at the pretraining budget, RC
# only, CF only, the forgetting check; `make experiment` then adds KITTI easy/moderate/hard of
# every row and writes the reports (every finished stage is skipped)
make -j2 controls baselines cross-domain $V "$T"
make experiment SEEDS=0 TRAIN_FLAGS="--threads 1"
