#!/bin/bash
# forgetting check of x2 with source size sn on the source validation set shifted as it was trained
# (dali size-norm --like-model), seed $1, demo3-s$1; compare with iter0/eval_source (source only)
set -e
s=$1
D=.venv/bin/dali; R=runs/demo3-s$s; A=$R/ablations/x2_srcsn
E="--protocol range --front-only --iou 0.7 --iou 0.5 --score-min 0.3"
$D size-norm --data $R/data/source_val --like-model $A/model --out $A/source_val_sized
$D eval --model $A/model --data $A/source_val_sized --scale 1.0 $E --out $A/eval_source_sized
