#!/bin/bash
# A new seed (new data) for the three decisive rows, through the Makefile's targets with the
# defaults of session 14 (label options on, retraining split 3 + 9): the x2-budget control, x2
# (`make iter2`) and x1 long (`make x1-long`), then each on the seed's 400-frame validation set
# under the row names of the seeds before (fitomlate = x2, fitomlong = x1 long; links in runs/).
# Usage: seed_job.sh SEED   (from a worktree with runs/; logs in logs/)
set -e
cd "$(dirname "$0")/../../.."
s=$1; R=runs/d5-s$s
COMMON="SEED=$s FRAMES=48 VAL_FRAMES=48 TRAIN_FLAGS=--threads=1 SYNTH_WORKERS=1 WORKERS=1 EPOCHS=6"
mkdir -p logs
make --no-print-directory data $R/library/manifest.json RUN=$R $COMMON
make --no-print-directory $R/iter0/model/manifest.json RUN=$R $COMMON
( make --no-print-directory $R/baselines/source_x2_budget/ptsn/manifest.json RUN=$R $COMMON > logs/s${s}control.log 2>&1 ) &
make --no-print-directory $R/iter1/rc/manifest.json $R/iter1/cf/manifest.json RUN=$R $COMMON
( make --no-print-directory $R/x1_long/ptsn/manifest.json RUN=$R $COMMON > logs/s${s}long.log 2>&1 ) &
make --no-print-directory $R/iter2/model/manifest.json $R/iter3/ptsn/manifest.json RUN=$R $COMMON
wait
mkdir -p runs/d5fitomlate-s$s runs/d5fitomlong-s$s
for d in iter2 iter3; do [ -e runs/d5fitomlate-s$s/$d ] || ln -s $(realpath $R/$d) runs/d5fitomlate-s$s/$d; done
for d in model ptsn; do [ -e runs/d5fitomlong-s$s/$d ] || ln -s $(realpath $R/x1_long/$d) runs/d5fitomlong-s$s/$d; done
docs/results/demo6/val400_job.sh $s control fitomlate fitomlong
echo "DONE seed $s $(date)"
