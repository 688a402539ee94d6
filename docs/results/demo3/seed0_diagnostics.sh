#!/bin/bash
# E2: x1 with PPCG built from the TRUE target boxes (diagnostic upper bound), seed 0
set -e
D=.venv/bin/dali; R=runs/demo3-s0; A=$R/ablations/x1_gtboxes
$D ppcg-rc --target $R/data/target --boxes $R/data/target --library $R/library --target-profile kitti --seed 0 --workers 1 --out $A/rc
$D ppcg-cf --target $R/data/target --boxes $R/data/target --library $R/library --target-profile kitti --seed 0 --workers 1 --out $A/cf
$D retrain --init $R/iter0/model --source $R/data/source --ppcg $A/rc $A/cf --seed 0 --epochs 6 --threads 1 --no-progress --out $A/model
$D ptsn-sweep --model $A/model --target $R/data/target --expected-size sn --score-min 0.3 --seed 0 --out $A/ptsn
$D eval --model $A/model --data $R/data/target_val --scale-from $A/ptsn --protocol range --front-only --iou 0.7 --iou 0.5 --score-min 0.3 --out $A/eval
#!/bin/bash
# E6: x1 retrained on source + RAW target frames with TRUE labels (no PPCG): upper bound of the retraining step, seed 0
set -e
D=.venv/bin/dali; R=runs/demo3-s0; A=$R/ablations/x1_rawtarget_gt
$D retrain --init $R/iter0/model --source $R/data/source --ppcg $R/data/target --seed 0 --epochs 6 --threads 1 --no-progress --out $A/model
$D ptsn-sweep --model $A/model --target $R/data/target --expected-size sn --score-min 0.3 --seed 0 --out $A/ptsn
$D eval --model $A/model --data $R/data/target_val --scale-from $A/ptsn --protocol range --front-only --iou 0.7 --iou 0.5 --score-min 0.3 --out $A/eval
#!/bin/bash
# E3: x1 with source SN + retrain peak lr 2e-3, seed 0
set -e
D=.venv/bin/dali; R=runs/demo3-s0; A=$R/ablations/x1_srcsn_lr2e-3
$D retrain --init $R/iter0/model --source $R/data/source --ppcg $R/iter1/rc $R/iter1/cf --source-size sn --target-profile kitti --lr 2e-3 --seed 0 --epochs 6 --threads 1 --no-progress --out $A/model
$D ptsn-sweep --model $A/model --target $R/data/target --expected-size sn --score-min 0.3 --seed 0 --out $A/ptsn
$D eval --model $A/model --data $R/data/target_val --scale-from $A/ptsn --protocol range --front-only --iou 0.7 --iou 0.5 --score-min 0.3 --out $A/eval
#!/bin/bash
# E8: iteration 2 from the default x1 with its iter2 PPCG, peak lr 1e-3 (fine-tune instead of a warm restart), seed 0
set -e
D=.venv/bin/dali; R=runs/demo3-s0; A=$R/ablations/x2_lr1e-3
$D retrain --init $R/iter1/model --source $R/data/source --ppcg $R/iter2/rc $R/iter2/cf --lr 1e-3 --seed 0 --epochs 6 --threads 1 --no-progress --out $A/model
$D ptsn-sweep --model $A/model --target $R/data/target --expected-size sn --score-min 0.3 --seed 0 --out $A/ptsn
$D eval --model $A/model --data $R/data/target_val --scale-from $A/ptsn --protocol range --front-only --iou 0.7 --iou 0.5 --score-min 0.3 --out $A/eval
