#!/bin/bash
# Where does the retraining lose? x1 with x2's training frames in one long retraining (12 epochs of
# source + 48-frame sets 1:1 from the pretrained model, source size sn), with its PPCG built (b) from
# the TRUE target boxes instead of the pseudo boxes, and (c) replaced by the raw target frames with
# their true labels. Diagnostics that read target labels (never a DALI default). Usage: decomp_job.sh SEED
set -e
cd "$(dirname "$0")/../../.."

s=$1; R=runs/d5-s$s; D=.venv/bin/dali
RETRAIN="--init $R/iter0/model --source $R/data/source --source-size sn --target-size-from $R/iter1/ptsn --seed $s --epochs 12 --threads 1 --no-progress"
EVAL="--data $R/data/target_val --protocol range --front-only --iou 0.7 --iou 0.5 --score-min 0.3"
finish() {  # $1: dir holding model/: its own PTSN sweep and the evaluation at that scale
  $D ptsn-sweep --model $1/model --target $R/data/target --expected-size sn --score-min 0.3 --seed $s --out $1/ptsn
  $D eval --model $1/model $EVAL --scale-from $1/ptsn --out $1/eval
}
A=runs/d5truebox-s$s
$D ppcg-rc --target $R/data/target --boxes $R/data/target --library $R/library --target-profile kitti --seed $s --out $A/rc
$D ppcg-cf --target $R/data/target --boxes $R/data/target --library $R/library --target-profile kitti --seed $s --out $A/cf
$D retrain $RETRAIN --ppcg $A/rc $A/cf --out $A/model
finish $A
B=runs/d5rawtrue-s$s
$D retrain $RETRAIN --ppcg $R/data/target --out $B/model
finish $B
echo "DONE decomp $s $(date)"
