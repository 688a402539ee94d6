# Sourced by hybrid_job.sh, refine_job.sh and docs/results/demo7/truthpose_job.sh (from the
# repository root, with s=SEED and R=runs/d5-s$s set): x1 with x2's frames in one long retraining,
# its PPCG built from the boxes in A/boxes, then the sweep and the 400-frame validation row ROW.
#   long_row A ROW
long_row() {
  local A=$1 row=$2 D=.venv/bin/dali
  local RETRAIN="--init $R/iter0/model --source $R/data/source --source-size sn --target-size-from $R/iter1/ptsn --seed $s --epochs 12 --threads 1 --no-progress"
  local PPCG="--target $R/data/target --boxes $A/boxes --library $R/library --target-profile kitti --seed $s --workers 1"
  $D ppcg-rc $PPCG --out $A/rc
  $D ppcg-cf $PPCG --out $A/cf
  $D retrain $RETRAIN --ppcg $A/rc $A/cf --out $A/model
  $D ptsn-sweep --model $A/model --target $R/data/target --expected-size sn --score-min 0.3 --seed $s --out $A/ptsn
  docs/results/demo6/val400_job.sh $s $row
}
