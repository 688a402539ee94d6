#!/bin/bash
# x1 with source size sn whose RC also re-casts the dense pseudo boxes (--max-points 1000000;
# default 300: dense boxes keep their raw points), seed $1, demo3-s$1. Compare with ablations/x1_srcsn.
set -e
s=$1
D=.venv/bin/dali; R=runs/demo3-s$s; B=$R/ablations; A=$B/x1_srcsn_rc_dense
E="--protocol range --front-only --iou 0.7 --iou 0.5 --score-min 0.3"
SN="--source-size sn --target-profile kitti"
$D ppcg-rc --target $R/data/target --boxes $R/iter1/pseudo --library $R/library --target-profile kitti --seed $s --workers 1 --max-points 1000000 --no-progress --out $A/rc
$D retrain --init $R/iter0/model --source $R/data/source --ppcg $A/rc $R/iter1/cf $SN --seed $s --epochs 6 --threads 1 --no-progress --out $A/model
$D ptsn-sweep --model $A/model --target $R/data/target --expected-size sn --score-min 0.3 --seed $s --out $A/ptsn
$D eval --model $A/model --data $R/data/target_val --scale-from $A/ptsn $E --out $A/eval
$D eval --pred $A/eval/predictions.parquet --gt $R/data/target_val --protocol kitti --iou 0.7 --iou 0.5 --score-min 0.3 --out $A/eval/metrics_kitti.json
