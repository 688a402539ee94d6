#!/bin/bash
# x1-level ablations of one demo seed (equal frames: 576 retraining frames each), sharing
# runs/d5-s$SEED's data, pretrained model and iteration-1 pseudo labels. Usage: abl_job.sh SEED
set -e
cd "$(dirname "$0")/../../.."

s=$1; R=runs/d5-s$s
COMMON="SEED=$s FRAMES=48 VAL_FRAMES=48 SYNTH_WORKERS=1 WORKERS=1 EPOCHS=6"
link() {  # $1 RUN, then the subpaths of R to link
  local run=$1; shift
  for p in "$@"; do mkdir -p $(dirname $run/$p); [ -e $run/$p ] || ln -s $(realpath $R/$p) $run/$p; done
}
# CF moving each box to 40-80 m (default 20-50 m) before its scan: sparser, far-range-like cars
C=runs/d5cf80-s$s; link $C data library iter0/model iter1/ptsn iter1/pseudo iter1/rc
[ -f $C/iter1/cf/manifest.json ] || .venv/bin/dali ppcg-cf --target $R/data/target --boxes $R/iter1/pseudo --library $R/library --target-profile kitti --seed $s --range-m 40:80 --out $C/iter1/cf
make --no-print-directory $C/iter1/eval/manifest.json RUN=$C RETRAIN_EPOCHS=6 TRAIN_FLAGS=--threads=1 $COMMON
# point models from the dense source instances instead of procedural meshes
P=runs/d5pts-s$s; link $P data iter0/model iter1/ptsn iter1/pseudo
[ -f $P/library/manifest.json ] || .venv/bin/dali library build --points $R/data/source --out $P/library
make --no-print-directory $P/iter1/eval/manifest.json RUN=$P RETRAIN_EPOCHS=6 TRAIN_FLAGS=--threads=1 $COMMON
# source:PPCG 1:3 (3 epochs of 48 + 144 frames = 576 frames)
M=runs/d5mix13-s$s; link $M data library iter0/model iter1/ptsn iter1/pseudo iter1/rc iter1/cf
make --no-print-directory $M/iter1/eval/manifest.json RUN=$M RETRAIN_EPOCHS=3 TRAIN_FLAGS="--threads=1 --mix=1:3" $COMMON
# retraining from a fresh network (the authors' code)
S=runs/d5scratch-s$s; link $S data library iter0/model iter1/ptsn iter1/pseudo iter1/rc iter1/cf
make --no-print-directory $S/iter1/eval/manifest.json RUN=$S RETRAIN_EPOCHS=6 TRAIN_FLAGS="--threads=1 --init-from=scratch" $COMMON
echo "DONE abl $s $(date)"
