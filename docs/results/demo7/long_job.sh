#!/bin/bash
# x1 with x2's frames in one long retraining (12 epochs; as docs/results/demo6/refine_job.sh) on
# the iteration-1 PPCG frames of fit_job.sh's row ROW (fit: --fit-points; fito: also
# --orient-models), then PTSN and the 400-frame validation (val400_job.sh SEED ROWlong).
# Usage: long_job.sh SEED fit|fito|fitom   (needs runs/d5ROW-s$SEED/iter1/{rc,cf})
set -e
cd "$(dirname "$0")/../../.."

s=$1; row=$2; R=runs/d5-s$s; P=runs/d5$row-s$s/iter1; A=runs/d5${row}long-s$s; D=.venv/bin/dali
until [ -e $P/cf/manifest.json ] && [ -e $P/rc/manifest.json ]; do sleep 30; done
$D retrain --init $R/iter0/model --source $R/data/source --ppcg $P/rc $P/cf --source-size sn \
  --target-size-from $R/iter1/ptsn --seed $s --epochs 12 --threads 1 --no-progress --out $A/model
$D ptsn-sweep --model $A/model --target $R/data/target --expected-size sn --score-min 0.3 --seed $s --out $A/ptsn
docs/results/demo6/val400_job.sh $s ${row}long
echo "DONE ${row}long $s $(date)"
