#!/bin/bash
# SN (source boxes shifted to the target's mean size, points with them) trained on x2's 1,440
# frames: retraining without PPCG at x2's budget. Evaluated at s = 1 and with test-time PTSN.
set -e
cd "$(dirname "$0")/../../.."

s=$1; R=runs/d5-s$s; S=runs/d5snx2-s$s
mkdir -p $S; [ -e $S/data ] || ln -s $(realpath $R/data) $S/data
make --no-print-directory $S/baselines/sn/eval/manifest.json $S/baselines/sn/eval_ptsn/manifest.json RUN=$S SEED=$s FRAMES=48 VAL_FRAMES=48 EPOCHS=30 TRAIN_FLAGS=--threads=1 WORKERS=1
echo "DONE snx2 $s $(date)"
