#!/bin/bash
# the benchmark's target, item 6: one seed of the full synthetic benchmark with ALL its rows (x2, x1 long, both
# equal-budget controls, the x2-budget oracle, SN, ROS, the pretraining-budget oracle, RC only,
# CF only, forgetting, KITTI protocol, compare, reports), timed from data synthesis to the
# report: `make experiment` with two core-pinned lanes (EXPERIMENT_LANES=2) and bf16 autocast in
# every model stage (PRECISION=bf16), on a 2-core machine with nothing else running.
#   bash docs/results/exp600/timing_job.sh   # from the repository root of a clean clone;
#                                            # resumable (make skips finished stages)
# Writes runs/experiment-s0 (and runs/experiment-report) and runs/timing/{experiment.log,times.txt}.
set -euo pipefail
LOGS=runs/timing
mkdir -p $LOGS
stamp() { echo "$1 $(date -u +%FT%TZ) load $(cut -d' ' -f1-3 /proc/loadavg)" | tee -a $LOGS/times.txt; }
stamp "start cpu=$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs) cores=$(nproc)"
make experiment SEEDS=${SEED:-0} EXPERIMENT_LANES=2 PRECISION=bf16 > $LOGS/experiment.log 2>&1
stamp end
