#!/bin/bash
# A fourth seed (new data, seed 3) for the two decisive rows: the x2-budget control and x1 long
# with --fit-points, --orient-models, --point-margin-m 0.3, through the Makefile targets, then both
# on its 400-frame validation set. Usage: seed3_job.sh (from a worktree with runs/)
set -e
cd "$(dirname "$0")/../../.."
s=3; R=runs/d5-s$s; L=runs/d5s3long
COMMON="SEED=$s FRAMES=48 VAL_FRAMES=48 TRAIN_FLAGS=--threads=1 SYNTH_WORKERS=1 WORKERS=1 EPOCHS=6 RETRAIN_EPOCHS=6"
make --no-print-directory data $R/library/manifest.json RUN=$R $COMMON
make --no-print-directory $R/iter0/model/manifest.json RUN=$R $COMMON
( taskset -c 0 make --no-print-directory $R/baselines/source_x2_budget/ptsn/manifest.json RUN=$R $COMMON > logs/s3control.log 2>&1; echo "control done $(date)" >> logs/s3control.log ) &
mkdir -p $L/iter0
for d in data library; do [ -e $L/$d ] || ln -s $(realpath $R/$d) $L/$d; done
[ -e $L/iter0/model ] || ln -s $(realpath $R/iter0/model) $L/iter0/model
taskset -c 1 make --no-print-directory $L/iter1/model/manifest.json $L/iter2/ptsn/manifest.json RUN=$L $COMMON RETRAIN_EPOCHS_1=12 PSEUDO_FLAGS=--fit-points PPCG_FLAGS="--orient-models --point-margin-m 0.3" > logs/s3long.log 2>&1
mkdir -p runs/d5fitomlong-s3
[ -e runs/d5fitomlong-s3/model ] || ln -s $(realpath $L/iter1/model) runs/d5fitomlong-s3/model
[ -e runs/d5fitomlong-s3/ptsn ] || ln -s $(realpath $L/iter2/ptsn) runs/d5fitomlong-s3/ptsn
wait
docs/results/demo6/val400_job.sh $s control fitomlong > logs/s3val400.log 2>&1
echo "DONE seed3 $(date)"
