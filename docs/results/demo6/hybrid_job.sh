#!/bin/bash
# Which property of the true boxes makes PPCG pay (session 11: +5.3 over the control)? x1 with x2's
# frames in one long retraining (as decomp_job.sh), its PPCG built from (a) the iteration-1 pseudo
# boxes that match a car (false boxes dropped, pseudo placement kept) and (b) the true boxes of
# the same cars. Diagnostics that read target labels (never a DALI default). Usage: hybrid_job.sh SEED
set -e
cd "$(dirname "$0")/../../.."

s=$1; R=runs/d5-s$s; D=.venv/bin/dali; P=.venv/bin/python
RETRAIN="--init $R/iter0/model --source $R/data/source --source-size sn --target-size-from $R/iter1/ptsn --seed $s --epochs 12 --threads 1 --no-progress"
for mode in pseudo-matched truth-matched; do
  A=runs/d5$mode-s$s
  [ -e $A/boxes/boxes.parquet ] || $P docs/results/demo6/hybrid_boxes.py --truth $R/data/target --pseudo $R/iter1/pseudo --mode $mode --out $A/boxes
  $D ppcg-rc --target $R/data/target --boxes $A/boxes --library $R/library --target-profile kitti --seed $s --workers 1 --out $A/rc
  $D ppcg-cf --target $R/data/target --boxes $A/boxes --library $R/library --target-profile kitti --seed $s --workers 1 --out $A/cf
  $D retrain $RETRAIN --ppcg $A/rc $A/cf --out $A/model
  $D ptsn-sweep --model $A/model --target $R/data/target --expected-size sn --score-min 0.3 --seed $s --out $A/ptsn
  docs/results/demo6/val400_job.sh $s $mode
done
echo "DONE hybrid $s $(date)"
