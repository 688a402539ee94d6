#!/bin/bash
set -e
s=$1
D=.venv/bin/dali; R=runs/demo3-s$s; A=$R/ablations/x2_srcsn
E="--protocol range --front-only --iou 0.7 --iou 0.5 --score-min 0.3"
$D pseudo-label --model $A/model --target $R/data/target --scale-from $A/ptsn --score-min 0.3 --out $A/pseudo_iter3
$D self-train --init $A/model --target $R/data/target --pseudo $A/pseudo_iter3 --seed $s --epochs 6 --lr 1e-3 --threads 1 --no-progress --out $A/st/model
$D eval --model $A/st/model --data $R/data/target_val --scale-from $A/ptsn $E --out $A/st/eval
$D eval --pred $A/st/eval/predictions.parquet --gt $R/data/target_val --protocol kitti --iou 0.7 --iou 0.5 --score-min 0.3 --out $A/st/eval/metrics_kitti.json
