#!/bin/bash
# x2 with --source-size sn in both iterations (label-free E_est of the kitti profile), seed $1, demo3-s$1
set -e
s=$1
D=.venv/bin/dali; R=runs/demo3-s$s; B=$R/ablations
E="--protocol range --front-only --iou 0.7 --iou 0.5 --score-min 0.3"
SN="--source-size sn --target-profile kitti"
$D retrain --init $R/iter0/model --source $R/data/source --ppcg $R/iter1/rc $R/iter1/cf $SN --seed $s --epochs 6 --threads 1 --no-progress --out $B/x1_srcsn/model
$D ptsn-sweep --model $B/x1_srcsn/model --target $R/data/target --expected-size sn --score-min 0.3 --seed $s --out $B/x1_srcsn/ptsn
$D eval --model $B/x1_srcsn/model --data $R/data/target_val --scale-from $B/x1_srcsn/ptsn $E --out $B/x1_srcsn/eval
A=$B/x2_srcsn
$D pseudo-label --model $B/x1_srcsn/model --target $R/data/target --scale-from $B/x1_srcsn/ptsn --score-min 0.3 --out $A/pseudo
$D ppcg-rc --target $R/data/target --boxes $A/pseudo --library $R/library --target-profile kitti --seed $s --workers 1 --out $A/rc
$D ppcg-cf --target $R/data/target --boxes $A/pseudo --library $R/library --target-profile kitti --seed $s --workers 1 --out $A/cf
$D retrain --init $B/x1_srcsn/model --source $R/data/source --ppcg $A/rc $A/cf $SN --seed $s --epochs 6 --threads 1 --no-progress --out $A/model
$D ptsn-sweep --model $A/model --target $R/data/target --expected-size sn --score-min 0.3 --seed $s --out $A/ptsn
$D eval --model $A/model --data $R/data/target_val --scale-from $A/ptsn $E --out $A/eval
for d in $B/x1_srcsn/eval $A/eval; do $D eval --pred $d/predictions.parquet --gt $R/data/target_val --protocol kitti --iou 0.7 --iou 0.5 --score-min 0.3 --out $d/metrics_kitti.json; done
$D eval --model $A/model --data $R/data/source_val --scale 1.0 $E --out $A/eval_source
