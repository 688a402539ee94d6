#!/bin/bash
# Diagnostic (reads target labels): x1 with x2's frames in one long retraining (as
# docs/results/demo6/hybrid_job.sh), its PPCG built from the cars the fitted iteration-1 pseudo
# labels found (runs/d5fit-s$SEED, fit_job.sh) at their TRUE pose with the PSEUDO size
# (hybrid_boxes.py --mode truth-pose). Compare with truth-matched (true pose and size) and fitlong (pseudo both).
# Usage: truthpose_job.sh SEED
set -e
cd "$(dirname "$0")/../../.."
source docs/results/demo6/long_row.sh

s=$1; R=runs/d5-s$s; A=runs/d5truthpose-s$s
[ -e $A/boxes/boxes.parquet ] || .venv/bin/python docs/results/demo6/hybrid_boxes.py --truth $R/data/target --pseudo runs/d5fit-s$s/iter1/pseudo --mode truth-pose --out $A/boxes
long_row $A truthpose
echo "DONE truthpose $s $(date)"
