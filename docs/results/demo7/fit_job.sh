#!/bin/bash
# x2 with point-fitted pseudo labels (dali pseudo-label --fit-points, dali_cli.labels.box_fit) in both
# iterations, the default chain otherwise (pretraining 288 frames, each retraining 576); reuses
# runs/d5-s$SEED's data, library, iteration-0 model and first sweep (docs/results/demo5/seed_job.sh),
# then evaluates on the 400-frame validation set (docs/results/demo6/val400_job.sh SEED ROW).
# ROW fit: --fit-points; fito: also ppcg-rc/ppcg-cf --orient-models (dali_cli.ppcg.orient);
# fitom: also --point-margin-m 0.3.
# Usage: fit_job.sh SEED [fit|fito|fitom]
set -e
cd "$(dirname "$0")/../../.."

s=$1; row=${2:-fit}; R=runs/d5-s$s; Q=runs/d5$row-s$s
declare -A PPCG=([fit]="" [fito]="--orient-models" [fitom]="--orient-models --point-margin-m 0.3")
ppcg=${PPCG[$row]}
COMMON="SEED=$s FRAMES=48 VAL_FRAMES=48 TRAIN_FLAGS=--threads=1 SYNTH_WORKERS=1 WORKERS=1"
mkdir -p $Q/iter1
for d in data library iter0; do [ -e $Q/$d ] || ln -s $(realpath $R/$d) $Q/$d; done
[ -e $Q/iter1/ptsn ] || ln -s $(realpath $R/iter1/ptsn) $Q/iter1/ptsn
make --no-print-directory iter2 RUN=$Q EPOCHS=6 RETRAIN_EPOCHS=6 PSEUDO_FLAGS=--fit-points PPCG_FLAGS="$ppcg" $COMMON
docs/results/demo6/val400_job.sh $s $row
echo "DONE $row $s $(date)"
