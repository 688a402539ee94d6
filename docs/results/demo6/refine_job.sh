#!/bin/bash
# x1 with x2's frames in one long retraining (as docs/results/demo5/decomp_job.sh), its PPCG built
# from the iteration-1 pseudo boxes moved to fit their points (refine_boxes.py; target points
# only, no label), evaluated on the 400-frame validation set. Usage: refine_job.sh SEED
set -e
cd "$(dirname "$0")/../../.."
source docs/results/demo6/long_row.sh

s=$1; R=runs/d5-s$s; A=runs/d5refined-s$s
[ -e $A/boxes/boxes.parquet ] || .venv/bin/python docs/results/demo6/refine_boxes.py --target $R/data/target --pseudo $R/iter1/pseudo --out $A/boxes
long_row $A refined
echo "DONE refined $s $(date)"
