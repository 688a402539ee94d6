#!/bin/bash
# Which property of the true boxes makes PPCG pay (session 11: +5.3 over the control)? x1 with x2's
# frames in one long retraining (as decomp_job.sh), its PPCG built from (a) the iteration-1 pseudo
# boxes that match a car (false boxes dropped, pseudo placement kept) and (b) the true boxes of
# the same cars. Diagnostics that read target labels (never a DALI default). Usage: hybrid_job.sh SEED
set -e
cd "$(dirname "$0")/../../.."
source docs/results/demo6/long_row.sh

s=$1; R=runs/d5-s$s; P=.venv/bin/python
for mode in pseudo-matched truth-matched; do
  A=runs/d5$mode-s$s
  [ -e $A/boxes/boxes.parquet ] || $P docs/results/demo6/hybrid_boxes.py --truth $R/data/target --pseudo $R/iter1/pseudo --mode $mode --out $A/boxes
  long_row $A $mode
done
echo "DONE hybrid $s $(date)"
