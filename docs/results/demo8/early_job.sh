#!/bin/bash
# x2 with the three label options (now the stages' defaults) and x2's 1,440 frames split 288
# pretraining + 864 (iteration 1, 9 epochs) + 288 (iteration 2, 3 epochs, on the better labels of
# the longer-trained iteration-1 model): row "fitomearly" (iteration 2 with the default peak lr
# 5e-3) and row "fitomearlyft" (the same iteration-2 frames, peak lr 1e-3: a fine-tune of the
# iteration-1 model rather than a second full cycle). Reuses runs/d5-s$SEED's data, library,
# iteration-0 model and the iteration-1 labels and PPCG frames of runs/d5fitom-s$SEED (or
# runs/d5s3long for seed 3), then evaluates both on the 400-frame validation set.
# Usage: early_job.sh SEED   (from a worktree with runs/)
set -e
cd "$(dirname "$0")/../../.."

s=$1; R=runs/d5-s$s; A=runs/d5fitomearly-s$s; B=runs/d5fitomearlyft-s$s
P=runs/d5fitom-s$s; [ $s = 3 ] && P=runs/d5s3long
COMMON="SEED=$s FRAMES=48 VAL_FRAMES=48 SYNTH_WORKERS=1 WORKERS=1 EPOCHS=6 RETRAIN_EPOCHS_1=9 RETRAIN_EPOCHS_2=3"
mkdir -p $A/iter1 $B/iter2
for d in data library iter0; do [ -e $A/$d ] || ln -s $(realpath $R/$d) $A/$d; done
for d in ptsn pseudo rc cf; do [ -e $A/iter1/$d ] || ln -s $(realpath $P/iter1/$d) $A/iter1/$d; done
make --no-print-directory $A/iter2/rc/manifest.json $A/iter2/cf/manifest.json RUN=$A $COMMON TRAIN_FLAGS=--threads=1
for d in data library iter0 iter1; do [ -e $B/$d ] || ln -s $(realpath $A/$d) $B/$d; done
for d in ptsn pseudo rc cf; do [ -e $B/iter2/$d ] || ln -s $(realpath $A/iter2/$d) $B/iter2/$d; done
make --no-print-directory $A/iter3/ptsn/manifest.json RUN=$A $COMMON TRAIN_FLAGS=--threads=1 &
make --no-print-directory $B/iter3/ptsn/manifest.json RUN=$B $COMMON TRAIN_FLAGS="--threads=1 --lr 1e-3"
wait
docs/results/demo6/val400_job.sh $s fitomearly fitomearlyft
echo "DONE early $s $(date)"
