#!/bin/bash
# Pseudo labels with test-time augmentation (dali pseudo-label --tta: ŝ x 0.9..1.1, each also
# mirrored, fused). "tta": the default x2 chain (pretraining 288 frames, each retraining 576);
# "ttalate": x2's 1,440 frames as 288 + 288 (3 epochs) + 864 (9 epochs). Reuses runs/d5-s$SEED's
# data, library, iteration-0 model and first sweep (docs/results/demo5/seed_job.sh).
# Usage: tta_job.sh SEED [tta|ttalate]...
set -e
cd "$(dirname "$0")/../../.."

s=$1; shift; R=runs/d5-s$s; D=.venv/bin/dali
COMMON="SEED=$s FRAMES=48 VAL_FRAMES=48 TRAIN_FLAGS=--threads=1 SYNTH_WORKERS=1 WORKERS=1"
kitti() {  # $1: eval directory
  [ -e $1/metrics_kitti.json ] || $D eval --pred $1/predictions.parquet --gt $R/data/target_val \
    --protocol kitti --iou 0.7 --iou 0.5 --size-score-min 0.3 --out $1/metrics_kitti.json
}
link() {  # $1: new RUN sharing data, library, iteration 0 and the first sweep with $R
  mkdir -p $1/iter1
  for d in data library iter0; do [ -e $1/$d ] || ln -s $(realpath $R/$d) $1/$d; done
  [ -e $1/iter1/ptsn ] || ln -s $(realpath $R/iter1/ptsn) $1/iter1/ptsn
}
variants=${*:-tta ttalate}
for variant in $variants; do
  Q=runs/d5$variant-s$s; link $Q
  if [ $variant = tta ]; then
    make --no-print-directory iter2 RUN=$Q EPOCHS=6 RETRAIN_EPOCHS=6 PSEUDO_FLAGS=--tta $COMMON
    kitti $Q/iter1/eval; kitti $Q/iter2/eval
    continue
  fi
  T=runs/d5tta-s$s  # iteration 1's labels and PPCG frames are tta's
  make --no-print-directory $T/iter1/rc/manifest.json $T/iter1/cf/manifest.json RUN=$T EPOCHS=6 RETRAIN_EPOCHS=6 PSEUDO_FLAGS=--tta $COMMON
  init=$R/iter0/model
  for it in 1 2; do
    epochs=$([ $it = 1 ] && echo 3 || echo 9)
    if [ $it = 1 ]; then P=$T/iter1; ptsn=$R/iter1/ptsn; else P=$Q/iter2; ptsn=$Q/iter2/ptsn
      $D pseudo-label --tta --model $init --target $R/data/target --scale-from $ptsn --workers 1 --no-progress --out $P/pseudo
      $D ppcg-rc --target $R/data/target --boxes $P/pseudo --library $R/library --sensor kitti --seed $s --workers 1 --out $P/rc
      $D ppcg-cf --target $R/data/target --boxes $P/pseudo --library $R/library --sensor kitti --seed $s --workers 1 --out $P/cf
    fi
    $D retrain --init $init --source $R/data/source --ppcg $P/rc $P/cf --source-size sn --target-size-from $ptsn --seed $s --epochs $epochs --threads 1 --quiet --out $Q/iter$it/model
    $D ptsn-sweep --model $Q/iter$it/model --target $R/data/target --expected-size sn --score-min 0.3 --seed $s --out $Q/iter$((it+1))/ptsn
    init=$Q/iter$it/model
  done
  $D eval --model $Q/iter2/model --data $R/data/target_val --scale-from $Q/iter3/ptsn --protocol range --front-only --iou 0.7 --iou 0.5 --size-score-min 0.3 --out $Q/iter2/eval
  kitti $Q/iter2/eval
done
echo "DONE tta $s $* $(date)"
