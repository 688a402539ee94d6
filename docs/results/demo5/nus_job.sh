#!/bin/bash
# the nuScenes-like -> KITTI-like task at demo scale, seed 0: x1, x2, and the x2-budget controls
set -e
cd "$(dirname "$0")/../../.."

make --no-print-directory experiment SOURCE_SENSOR=nuscenes SEEDS=0 EXPERIMENT_PREFIX=runs/d5nus \
  EXPERIMENT_FRAMES=48 EXPERIMENT_VAL_FRAMES=48 EXPERIMENT_EPOCHS=6 EXPERIMENT_RETRAIN_EPOCHS=6 \
  EXPERIMENT_GOALS="iter2 controls-x2" EXPERIMENT_FIRST_SEED_GOALS= TRAIN_FLAGS=--threads=1 SYNTH_WORKERS=1 WORKERS=1
echo "DONE nus $(date)"
