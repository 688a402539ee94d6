#!/bin/bash
# Issue 18, item 6: one seed of the full synthetic benchmark, ALL rows (x2, x1 long, both
# equal-budget controls, the x2-budget oracle, SN, ROS, the pretraining-budget oracle, RC only,
# CF only, forgetting, KITTI protocol, compare, report), timed from data synthesis to the report
# on a 2-core machine: bf16 autocast in every model stage (PRECISION=bf16) and two lanes of
# about equal work (39,600 training frames in all), each pinned to one core (taskset: every stage
# in it, inference and ray casting included, then sees one core and runs one thread), then
# `make experiment` on both cores for what is left.
#   bash docs/results/exp600/timing_job.sh   # from the repository root of a clean clone;
#                                            # resumable (make skips finished stages)
# Writes runs/experiment-s0 and runs/timing/{lane_a,lane_b,final}.log and times.txt.
set -euo pipefail
SEED=${SEED:-0}
RUN=runs/experiment-s$SEED
V=(RUN=$RUN SEED=$SEED FRAMES=600 VAL_FRAMES=200 EPOCHS=4 RETRAIN_EPOCHS=2 PRECISION=bf16)
LOGS=runs/timing
mkdir -p $LOGS
stamp() { echo "$1 $(date -u +%FT%TZ) load $(cut -d' ' -f1-3 /proc/loadavg)" | tee -a $LOGS/times.txt; }
stamp "start cpu=$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs) cores=$(nproc)"
make data "${V[@]}" > $LOGS/data.log 2>&1  # first: a FrameSet has one writer
stamp data
# lane A: the DALI chain and what needs it (16,800 training frames and most of the inference)
( taskset -c 0 make iter2 x1-long ablation-rc ablation-cf baseline-ros "${V[@]}" > $LOGS/lane_a.log 2>&1
  stamp lane_a ) &
lane_a=$!
# lane B: the rows that need only the data (22,800 training frames)
( taskset -c 1 make controls-x2 controls-x1 baseline-sn baseline-oracle "${V[@]}" > $LOGS/lane_b.log 2>&1
  stamp lane_b ) &
lane_b=$!
wait $lane_a
wait $lane_b
# the rest (forgetting, KITTI protocol, compare, per-seed and aggregate reports)
make experiment SEEDS=$SEED PRECISION=bf16 > $LOGS/final.log 2>&1
stamp final
