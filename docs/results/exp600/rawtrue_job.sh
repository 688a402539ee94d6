#!/bin/bash
# Diagnostic (reads target labels; never a DALI default), seed 0 unless SEED: x1 long exactly as
# `make x1-long` (init iter0, source sized to E_est, source:set 1:1, 4 epochs = 4,800 frames) but
# with the raw target training frames and ALL their true labels in place of the PPCG frames. Against
# x1 long with PPCG from the true boxes (truth_job.sh, 86.0) and the x2-budget oracle (89.0): does
# the oracle's lead come from PPCG's synthetic car points, or from the schedule (2,400 source
# pretraining frames, then half the batches from the source)? At demo scale the two
# were level (+6.1 ± 3.2 and +5.3 ± 0.7 over the control).
#   bash docs/results/exp600/rawtrue_job.sh     # row V/x1_long/eval; resumable (stage manifests)
set -euo pipefail
SEED=${SEED:-0}
R=runs/experiment-s$SEED
V=$R/variants/x1long-rawtrue
D=.venv/bin/dali
$D retrain --init $R/iter0/model --source $R/data/source --ppcg $R/data/target --source-size sn \
    --target-size-from $R/iter1/ptsn --seed $SEED --epochs 4 --threads 1 --out $V/x1_long/model
$D ptsn-sweep --model $V/x1_long/model --target $R/data/target --expected-size sn --score-min 0.3 \
    --seed $SEED --out $V/x1_long/ptsn
$D eval --model $V/x1_long/model --data $R/data/target_val --scale-from $V/x1_long/ptsn \
    --protocol range --front-only --iou 0.7 --iou 0.5 --size-score-min 0.3 --out $V/x1_long/eval
$D eval --pred $V/x1_long/eval/predictions.parquet --gt $R/data/target_val --protocol kitti \
    --iou 0.7 --iou 0.5 --size-score-min 0.3 --out $V/x1_long/eval/metrics_kitti.json
