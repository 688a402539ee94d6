#!/bin/bash
# x2's 1,440 frames with the long retraining on x1's labels: pretraining 288 frames, iteration 1
# retraining 3 epochs (288 frames), iteration 2 retraining 9 epochs (864 frames). Usage: late_job.sh SEED
set -e
cd "$(dirname "$0")/../../.."

s=$1; R=runs/d5-s$s; Q=runs/d5late-s$s; D=.venv/bin/dali
init=$R/iter0/model; ptsn=$R/iter1/ptsn
for it in 1 2; do
  epochs=$([ $it = 1 ] && echo 3 || echo 9)
  if [ $it = 1 ]; then pseudo=$R/iter1/pseudo; rc=$R/iter1/rc; cf=$R/iter1/cf; else
    pseudo=$Q/iter2/pseudo; rc=$Q/iter2/rc; cf=$Q/iter2/cf
    $D pseudo-label --model $init --target $R/data/target --scale-from $ptsn --workers 1 --no-progress --out $pseudo
    $D ppcg-rc --target $R/data/target --boxes $pseudo --library $R/library --target-profile kitti --seed $s --out $rc
    $D ppcg-cf --target $R/data/target --boxes $pseudo --library $R/library --target-profile kitti --seed $s --out $cf
  fi
  $D retrain --init $init --source $R/data/source --ppcg $rc $cf --source-size sn --target-size-from $ptsn --seed $s --epochs $epochs --threads 1 --no-progress --out $Q/iter$it/model
  $D ptsn-sweep --model $Q/iter$it/model --target $R/data/target --expected-size sn --score-min 0.3 --seed $s --out $Q/iter$((it+1))/ptsn
  init=$Q/iter$it/model; ptsn=$Q/iter$((it+1))/ptsn
done
$D eval --model $Q/iter2/model --data $R/data/target_val --scale-from $Q/iter3/ptsn --protocol range --front-only --iou 0.7 --iou 0.5 --score-min 0.3 --out $Q/iter2/eval
$D eval --pred $Q/iter2/eval/predictions.parquet --gt $R/data/target_val --protocol kitti --iou 0.7 --iou 0.5 --score-min 0.3 --out $Q/iter2/eval/metrics_kitti.json
echo "DONE late $s $(date)"
