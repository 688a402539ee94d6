#!/bin/bash
# x1 with x2's frames in one long retraining (as docs/results/demo5/decomp_job.sh), its PPCG built
# from the iteration-1 pseudo boxes moved to fit their points (refine_boxes.py; target points
# only, no label), evaluated on the 400-frame validation set. Usage: refine_job.sh SEED
set -e
cd "$(dirname "$0")/../../.."

s=$1; R=runs/d5-s$s; D=.venv/bin/dali; A=runs/d5refined-s$s
RETRAIN="--init $R/iter0/model --source $R/data/source --source-size sn --target-size-from $R/iter1/ptsn --seed $s --epochs 12 --threads 1 --no-progress"
[ -e $A/boxes/boxes.parquet ] || .venv/bin/python docs/results/demo6/refine_boxes.py --target $R/data/target --pseudo $R/iter1/pseudo --out $A/boxes
$D ppcg-rc --target $R/data/target --boxes $A/boxes --library $R/library --target-profile kitti --seed $s --workers 1 --out $A/rc
$D ppcg-cf --target $R/data/target --boxes $A/boxes --library $R/library --target-profile kitti --seed $s --workers 1 --out $A/cf
$D retrain $RETRAIN --ppcg $A/rc $A/cf --out $A/model
$D ptsn-sweep --model $A/model --target $R/data/target --expected-size sn --score-min 0.3 --seed $s --out $A/ptsn
docs/results/demo6/val400_job.sh $s refined
echo "DONE refined $s $(date)"
