#!/bin/bash
# x2 with the same 1,440-frame budget spent front-loaded: pretraining 18 epochs (864 frames), each
# retraining 3 epochs of source + PPCG (288 frames), default settings otherwise (source size sn).
# Data and library copied from runs/demo3-s$1 (identical: synth is deterministic per seed), so the
# equal-budget controls of demo3 (X2_BUDGET = EPOCHS + 4 x RETRAIN_EPOCHS = 30 epochs) still apply.
set -e
s=$1; R=runs/demo5-s$s
mkdir -p $R
[ -d $R/data ] || cp -r runs/demo3-s$s/data $R/data
[ -d $R/library ] || cp -r runs/demo3-s$s/library $R/library
make --no-print-directory iter2 kitti-protocol RUN=$R SEED=$s FRAMES=48 VAL_FRAMES=48 EPOCHS=18 RETRAIN_EPOCHS=3 TRAIN_FLAGS=--threads=1 SYNTH_WORKERS=1
