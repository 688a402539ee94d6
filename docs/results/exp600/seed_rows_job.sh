#!/bin/bash
# a later run (the benchmark's target, item 3): a later run one label-free 1:7 gain on a second seed. Builds the
# seed's iteration-1 chain as `make experiment` would (600/600/200 frames, EPOCHS=4: iter0/model,
# iter1/ptsn, iter1/pseudo, iter1/rc, iter1/cf), then runs target_share_job.sh's two rows side by
# side, one core each: SET=ppcg MIX=1:7 EPOCHS=2 (PPCG from the default 0.3 boxes) and the same
# with LABELS=cut06 (`pseudo-label --score-min 0.6`). Then `dali compare` of the pair on the seed's
# 800 fresh validation frames, R40 and R400 -> runs/val800/experiment-s<SEED>/direct31_cut17_r*.json.
# Resumable: every step is an artifact directory. From the directory holding runs/:
#   SEED=1 bash docs/results/exp600/seed_rows_job.sh
# Start it unpinned (no taskset around it): the cut row's pseudo labels, RC and CF run in its
# subshell without a taskset of their own, and would share the other row's core.
set -euo pipefail
SEED=${SEED:-1}
HERE=$(cd "$(dirname "$0")" && pwd)
D=${DALI:-.venv/bin/dali}
R=runs/experiment-s$SEED
make -f "${MAKEFILE:-$HERE/../../../Makefile}" $R/iter1/rc/manifest.json $R/iter1/cf/manifest.json \
    RUN=$R SEED=$SEED SOURCE_SENSOR=waymo FRAMES=600 VAL_FRAMES=200 EPOCHS=4 RETRAIN_EPOCHS=2
V800=runs/val800/data-s$SEED  # made here, not by both rows at once (eval_row.sh's val800_row)
[ -f $V800/manifest.json ] || $D synth --sensor kitti --cars kitti --frames 800 \
    --seed $(( SEED + 5000 )) --executor local --workers 2 --out $V800
( SEED=$SEED SET=ppcg MIX=1:7 EPOCHS=2 DALI="taskset -c 0 $D" bash $HERE/target_share_job.sh ) &
A=$!
( SEED=$SEED LABELS=cut06 SET=ppcg MIX=1:7 EPOCHS=2 DALI="taskset -c 1 $D" bash $HERE/target_share_job.sh ) &
B=$!
wait $A; wait $B
O=runs/val800/experiment-s$SEED
for pos in 40 400; do
  $D compare --gt $V800 --pred "PPCG 1:7"=$O/x1long-ppcg-mix17-ep2/predictions.parquet \
    --pred "PPCG 1:7, cars from 0.6"=$O/x1long-ppcg-cut06-mix17-ep2/predictions.parquet \
    --protocol range --front-only --iou 0.7 --recall-positions $pos --samples 400 --seed 0 \
    --no-progress --out $O/direct31_cut17_r$pos.json
done
