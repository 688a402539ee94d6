#!/bin/bash
# x2's 1,440 frames spent mostly on the labeller: pretraining 18 epochs (864 frames), each
# retraining 3 epochs (288 frames) ("front"); and x1 with pretraining 24 epochs (1,152 frames) +
# one retraining of 288 frames ("front-x1"). Reuses runs/d5-s$SEED's data and library
# (docs/results/demo5/seed_job.sh). Usage: front_job.sh SEED
set -e
cd "$(dirname "$0")/../../.."

s=$1; R=runs/d5-s$s; D=.venv/bin/dali
COMMON="SEED=$s FRAMES=48 VAL_FRAMES=48 TRAIN_FLAGS=--threads=1 SYNTH_WORKERS=1 WORKERS=1"
kitti() {  # $1: eval directory
  [ -e $1/metrics_kitti.json ] || $D eval --pred $1/predictions.parquet --gt $R/data/target_val \
    --protocol kitti --iou 0.7 --iou 0.5 --score-min 0.3 --out $1/metrics_kitti.json
}
for variant in front front24; do
  Q=runs/d5$variant-s$s; mkdir -p $Q
  for d in data library; do [ -e $Q/$d ] || ln -s $(realpath $R/$d) $Q/$d; done
  if [ $variant = front ]; then
    make --no-print-directory iter2 RUN=$Q EPOCHS=18 RETRAIN_EPOCHS=3 $COMMON
    kitti $Q/iter1/eval; kitti $Q/iter2/eval
  else
    make --no-print-directory iter1 RUN=$Q EPOCHS=24 RETRAIN_EPOCHS=3 $COMMON
    kitti $Q/iter1/eval
  fi
  kitti $Q/iter0/eval_ptsn
done
echo "DONE front $s $(date)"
