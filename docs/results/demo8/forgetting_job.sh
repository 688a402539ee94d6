#!/bin/bash
# Forgetting check (issue 18: x2's source-validation AP_3D@0.7 at most 2 below source only) of
# ROW's final model, the commands of the Makefile's cross-domain targets: the source-only model
# (iteration 0) on the raw source validation set, ROW on the same frames shifted as its training
# shifted the source (dali size-norm --like-model; source size sn). 48 validation frames
# (seed SEED + 3000), built once in runs/d5-s$SEED/data.
# Usage: forgetting_job.sh SEED [MODEL_PARENT]   (default runs/d5fitomlate-s$SEED/iter2)
set -e
cd "$(dirname "$0")/../../.."
s=$1; R=runs/d5-s$s; A=${2:-runs/d5fitomlate-s$s/iter2}; D=.venv/bin/dali; V=$R/data/source_val
E="--protocol range --front-only --iou 0.7 --iou 0.5 --score-min 0.3 --workers 1"
[ -e $V/manifest.json ] || $D synth --sensor waymo --cars waymo --frames 48 --seed $((s + 3000)) --executor local --workers 1 --out $V
$D eval --model $R/iter0/model --data $V --scale 1.0 $E --out $R/iter0/eval_source
$D size-norm --data $V --like-model $A/model --out $A/source_val_sized
$D eval --model $A/model --data $A/source_val_sized --scale 1.0 $E --out $A/eval_source_sized
echo "DONE forgetting $s $A $(date)"
