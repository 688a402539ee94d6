#!/bin/bash
# Re-evaluate the demo-scale models of docs/results/demo5 and demo6 on a 400-frame validation set
# per seed (synthesized with seed SEED + 5000; the 48-frame set's evaluation noise dominated the
# session-11 error bars), each model at its own PTSN scale, range protocol and KITTI.
# Usage: val400_job.sh SEED [ROW...]   (ROW = name of a row below; default all)
set -e
cd "$(dirname "$0")/../../.."

s=$1; shift; R=runs/d5-s$s; D=.venv/bin/dali; V=$R/data/target_val400
[ -e $V/manifest.json ] || $D synth --sensor kitti --cars kitti --frames 400 --seed $((s + 5000)) --executor local --workers 1 --out $V
declare -A ROWS=(  # row -> "model_dir ptsn_dir"
  [control]="$R/baselines/source_x2_budget/model $R/baselines/source_x2_budget/ptsn"
  [x1]="$R/iter1/model $R/iter2/ptsn"
  [x2]="$R/iter2/model $R/iter3/ptsn"
  [x1long]="runs/d5long-s$s/iter1/model runs/d5long-s$s/iter2/ptsn"
  [late]="runs/d5late-s$s/iter2/model runs/d5late-s$s/iter3/ptsn"
  [truebox]="runs/d5truebox-s$s/model runs/d5truebox-s$s/ptsn"
  [rawtrue]="runs/d5rawtrue-s$s/model runs/d5rawtrue-s$s/ptsn"
  [front]="runs/d5front-s$s/iter2/model runs/d5front-s$s/iter3/ptsn"
  [front24]="runs/d5front24-s$s/iter1/model runs/d5front24-s$s/iter2/ptsn"
  [tta]="runs/d5tta-s$s/iter2/model runs/d5tta-s$s/iter3/ptsn"
  [ttalate]="runs/d5ttalate-s$s/iter2/model runs/d5ttalate-s$s/iter3/ptsn"
  [pseudo-matched]="runs/d5pseudo-matched-s$s/model runs/d5pseudo-matched-s$s/ptsn"
  [truth-matched]="runs/d5truth-matched-s$s/model runs/d5truth-matched-s$s/ptsn"
  [refined]="runs/d5refined-s$s/model runs/d5refined-s$s/ptsn"
  [fit]="runs/d5fit-s$s/iter2/model runs/d5fit-s$s/iter3/ptsn"
  [fito]="runs/d5fito-s$s/iter2/model runs/d5fito-s$s/iter3/ptsn"
  [fitlong]="runs/d5fitlong-s$s/model runs/d5fitlong-s$s/ptsn"
  [fitolong]="runs/d5fitolong-s$s/model runs/d5fitolong-s$s/ptsn"
  [fitom]="runs/d5fitom-s$s/iter2/model runs/d5fitom-s$s/iter3/ptsn"
  [fitomlong]="runs/d5fitomlong-s$s/model runs/d5fitomlong-s$s/ptsn"
  [fitomlate]="runs/d5fitomlate-s$s/iter2/model runs/d5fitomlate-s$s/iter3/ptsn"
  [fitomearly]="runs/d5fitomearly-s$s/iter2/model runs/d5fitomearly-s$s/iter3/ptsn"
  [fitomearlyft]="runs/d5fitomearlyft-s$s/iter2/model runs/d5fitomearlyft-s$s/iter3/ptsn"
  [truthpose]="runs/d5truthpose-s$s/model runs/d5truthpose-s$s/ptsn"
)
for row in ${*:-control x2 late tta ttalate x1long truebox rawtrue front front24 x1}; do
  set -- ${ROWS[$row]}; E=runs/val400-s$s/$row
  [ -e $1/manifest.json ] && [ -e $2/manifest.json ] || { echo "skip $row: $1 or $2 missing"; continue; }
  $D eval --model $1 --data $V --scale-from $2 --protocol range --front-only --iou 0.7 --iou 0.5 --score-min 0.3 --workers 1 --out $E
  [ -e $E/metrics_kitti.json ] || $D eval --pred $E/predictions.parquet --gt $V --protocol kitti --iou 0.7 --iou 0.5 --score-min 0.3 --out $E/metrics_kitti.json > /dev/null
done
echo "DONE val400 $s $(date)"
