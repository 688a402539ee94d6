#!/bin/bash
# x1 with x2's frames in one long retraining (as d5long: 12 epochs), pseudo labels at score >= 0.45
# instead of 0.3 (fewer hallucinated boxes, fewer true ones); all else default. Usage: score_job.sh SEED
set -e
cd "$(dirname "$0")/../../.."

s=$1; R=runs/d5-s$s; Q=runs/d5score45-s$s; D=.venv/bin/dali
$D pseudo-label --model $R/iter0/model --target $R/data/target --scale-from $R/iter1/ptsn --score-min 0.45 --workers 1 --no-progress --out $Q/pseudo
$D ppcg-rc --target $R/data/target --boxes $Q/pseudo --library $R/library --target-profile kitti --seed $s --out $Q/rc
$D ppcg-cf --target $R/data/target --boxes $Q/pseudo --library $R/library --target-profile kitti --seed $s --out $Q/cf
$D retrain --init $R/iter0/model --source $R/data/source --ppcg $Q/rc $Q/cf --source-size sn --target-size-from $R/iter1/ptsn --seed $s --epochs 12 --threads 1 --no-progress --out $Q/model
$D ptsn-sweep --model $Q/model --target $R/data/target --expected-size sn --score-min 0.3 --seed $s --out $Q/ptsn
$D eval --model $Q/model --data $R/data/target_val --scale-from $Q/ptsn --protocol range --front-only --iou 0.7 --iou 0.5 --score-min 0.3 --out $Q/eval
echo "DONE score $s $(date)"
