#!/bin/bash
# x2 (default schedule: 576 + 576 retraining frames) with pseudo labels at score >= 0.45 in both
# iterations; PTSN sweeps and evaluation unchanged (score 0.3). Usage: x2score_job.sh SEED
set -e
cd "$(dirname "$0")/../../.."

s=$1; R=runs/d5-s$s; Q=runs/d5x2score45-s$s; D=.venv/bin/dali
init=$R/iter0/model; ptsn=$R/iter1/ptsn
for it in 1 2; do
  $D pseudo-label --model $init --target $R/data/target --scale-from $ptsn --score-min 0.45 --workers 1 --no-progress --out $Q/iter$it/pseudo
  $D ppcg-rc --target $R/data/target --boxes $Q/iter$it/pseudo --library $R/library --target-profile kitti --seed $s --out $Q/iter$it/rc
  $D ppcg-cf --target $R/data/target --boxes $Q/iter$it/pseudo --library $R/library --target-profile kitti --seed $s --out $Q/iter$it/cf
  $D retrain --init $init --source $R/data/source --ppcg $Q/iter$it/rc $Q/iter$it/cf --source-size sn --target-size-from $ptsn --seed $s --epochs 6 --threads 1 --no-progress --out $Q/iter$it/model
  $D ptsn-sweep --model $Q/iter$it/model --target $R/data/target --expected-size sn --score-min 0.3 --seed $s --out $Q/iter$((it+1))/ptsn
  init=$Q/iter$it/model; ptsn=$Q/iter$((it+1))/ptsn
done
$D eval --model $Q/iter2/model --data $R/data/target_val --scale-from $Q/iter3/ptsn --protocol range --front-only --iou 0.7 --iou 0.5 --score-min 0.3 --out $Q/iter2/eval
echo "DONE x2score $s $(date)"
