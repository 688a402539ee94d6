#!/bin/bash
# training precision check: the x1-budget control of seed 0 trained with bf16 autocast,
# swept and evaluated in fp32 as the fp32 control was (runs/experiment-s0/baselines/source_x1_budget)
set -euo pipefail
R=runs/experiment-s0; V=$R/variants/control-x1-bf16
.venv/bin/dali pretrain --source $R/data/source --seed 0 --epochs 6 --threads 1 --precision bf16 --out $V/model
.venv/bin/dali ptsn-sweep --model $V/model --target $R/data/target --expected-size sn --score-min 0.3 --seed 0 --out $V/ptsn
.venv/bin/dali eval --model $V/model --data $R/data/target_val --scale-from $V/ptsn --protocol range --front-only --iou 0.7 --iou 0.5 --size-score-min 0.3 --executor local --out $V/eval_ptsn
