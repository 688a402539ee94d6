#!/bin/bash
# Diagnostic (reads target labels): x1 with x2's frames in one long retraining (as
# docs/results/demo6/hybrid_job.sh), its PPCG built from the cars the fitted iteration-1 pseudo
# labels found (runs/d5fit-s$SEED, fit_job.sh) at their TRUE pose with the PSEUDO size
# (hybrid_boxes.py --mode truth-pose). Compare with truth-matched (true pose and size) and fitlong (pseudo both).
# Usage: truthpose_job.sh SEED
set -e
cd "$(dirname "$0")/../../.."

s=$1; R=runs/d5-s$s; D=.venv/bin/dali; A=runs/d5truthpose-s$s
RETRAIN="--init $R/iter0/model --source $R/data/source --source-size sn --target-size-from $R/iter1/ptsn --seed $s --epochs 12 --threads 1 --no-progress"
[ -e $A/boxes/boxes.parquet ] || .venv/bin/python docs/results/demo6/hybrid_boxes.py --truth $R/data/target --pseudo runs/d5fit-s$s/iter1/pseudo --mode truth-pose --out $A/boxes
$D ppcg-rc --target $R/data/target --boxes $A/boxes --library $R/library --target-profile kitti --seed $s --workers 1 --out $A/rc
$D ppcg-cf --target $R/data/target --boxes $A/boxes --library $R/library --target-profile kitti --seed $s --workers 1 --out $A/cf
$D retrain $RETRAIN --ppcg $A/rc $A/cf --out $A/model
$D ptsn-sweep --model $A/model --target $R/data/target --expected-size sn --score-min 0.3 --seed $s --out $A/ptsn
docs/results/demo6/val400_job.sh $s truthpose
echo "DONE truthpose $s $(date)"
