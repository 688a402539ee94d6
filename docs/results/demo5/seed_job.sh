#!/bin/bash
# one demo-scale seed: default chain (x1, x2), x1 with x2's budget in one long retraining, the
# x2-budget control. Usage: seed_job.sh main SEED
set -e
cd "$(dirname "$0")/../../.."

kind=$1; s=$2
COMMON="SEED=$s FRAMES=48 VAL_FRAMES=48 TRAIN_FLAGS=--threads=1 SYNTH_WORKERS=1 WORKERS=1"
R=runs/d5-s$s
link_base() {  # $1: new RUN sharing data, library (and iter0 + iter1's PPCG when $2 = iter1)
  mkdir -p $1/iter0 $1/iter1
  for d in data library; do [ -e $1/$d ] || ln -s $(realpath $R/$d) $1/$d; done
  if [ "$2" = iter1 ]; then
    [ -e $1/iter0/model ] || ln -s $(realpath $R/iter0/model) $1/iter0/model
    for d in ptsn pseudo rc cf; do [ -e $1/iter1/$d ] || ln -s $(realpath $R/iter1/$d) $1/iter1/$d; done
  fi
}
if [ $kind = main ]; then
  make --no-print-directory iter1 RUN=$R EPOCHS=6 RETRAIN_EPOCHS=6 $COMMON
  L=runs/d5long-s$s; link_base $L iter1
  make --no-print-directory $L/iter1/eval/manifest.json RUN=$L EPOCHS=6 RETRAIN_EPOCHS=12 $COMMON
  make --no-print-directory $R/baselines/source_x2_budget/eval_ptsn/manifest.json RUN=$R EPOCHS=6 RETRAIN_EPOCHS=6 $COMMON
  make --no-print-directory iter2 RUN=$R EPOCHS=6 RETRAIN_EPOCHS=6 $COMMON
fi
echo "DONE $kind $s $(date)"
