#!/bin/bash
# Session 20: the size correction of an equal-budget control with E_pred from all the sweep's boxes
# (the default) and from its confident boxes only (`dali eval --size-factor-score-min`). The
# control's sweep is re-run into B/ptsn_s20 (sweeps before session 20 keep no detections.parquet;
# same ŝ), then its saved predictions are corrected and evaluated. Label-free but for the
# evaluation itself. From the repository root:
#   bash docs/results/exp600/confident_size_factors.sh runs/experiment-nuscenes-s0 x2 0
#   (RUN, budget x1|x2, the run's seed)
set -euo pipefail
R=$1; BUDGET=${2:-x2}; SEED=${3:-0}
D=${DALI:-.venv/bin/dali}
B=$R/baselines/source_${BUDGET}_budget
$D ptsn-sweep --model $B/model --target $R/data/target --expected-size sn --score-min 0.3 \
    --seed $SEED --out $B/ptsn_s20 --no-progress
for cut in all 0.5 0.7; do
    flag=""; [ $cut = all ] || flag="--size-factor-score-min $cut"
    $D eval --pred $B/eval_ptsn/predictions.parquet --gt $R/data/target_val --scale-from $B/ptsn_s20 \
        --size-correction per-dim $flag --protocol range --front-only --iou 0.7 --iou 0.5 \
        --out $B/eval_ptsn_sized_s20_$cut > /dev/null
    python3 - "$B/eval_ptsn_sized_s20_$cut/metrics.json" "$cut" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
print(f"E_pred from {sys.argv[2]}: AP_3D@0.7 {d['Car']['3d']['all']:.2f}, AP_BEV {d['Car']['bev']['all']:.2f}, "
      f"factors l/w/h {d['size_correction']['factors_lwh']}")
PY
done
