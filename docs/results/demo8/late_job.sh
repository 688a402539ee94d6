#!/bin/bash
# x2 with session 13's three label options (pseudo-label --fit-points; ppcg-rc/ppcg-cf
# --orient-models --point-margin-m 0.3) and x2's 1,440 frames split 288 pretraining + 288
# (iteration 1, 3 epochs) + 864 (iteration 2, 9 epochs, on iteration 1's better labels), through
# the Makefile targets. Reuses runs/d5-s$SEED's data, library and iteration-0 model and the
# iteration-1 labels and PPCG frames built with the same options (runs/d5fitom-s$SEED, or
# runs/d5s3long for seed 3), then evaluates on the 400-frame validation set (val400_job.sh).
# Usage: late_job.sh SEED   (from a worktree with runs/)
set -e
cd "$(dirname "$0")/../../.."

s=$1; R=runs/d5-s$s; Q=runs/d5fitomlate-s$s
P=runs/d5fitom-s$s; [ $s = 3 ] && P=runs/d5s3long
COMMON="SEED=$s FRAMES=48 VAL_FRAMES=48 TRAIN_FLAGS=--threads=1 SYNTH_WORKERS=1 WORKERS=1"
mkdir -p $Q/iter1
for d in data library iter0; do [ -e $Q/$d ] || ln -s $(realpath $R/$d) $Q/$d; done
for d in ptsn pseudo rc cf; do [ -e $Q/iter1/$d ] || ln -s $(realpath $P/iter1/$d) $Q/iter1/$d; done
make --no-print-directory $Q/iter2/model/manifest.json $Q/iter3/ptsn/manifest.json RUN=$Q EPOCHS=6 \
  RETRAIN_EPOCHS_1=3 RETRAIN_EPOCHS_2=9 PSEUDO_FLAGS=--fit-points \
  PPCG_FLAGS="--orient-models --point-margin-m 0.3" $COMMON
docs/results/demo6/val400_job.sh $s fitomlate
echo "DONE fitomlate $s $(date)"
