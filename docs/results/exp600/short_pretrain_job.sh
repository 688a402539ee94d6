#!/bin/bash
# a later run (the benchmark's target, item 3), seed 0 unless SEED: spend less of the equal budget on pretraining.
# a later run found the final model about as good as its last learning-rate schedule is long (the
# oracle pretrained 2,400 steps and retrained 4,800 with a fresh schedule = 4,800 from scratch),
# and x1 long's retraining about as good as labelled target training of its own length. So with
# the budget fixed (12 epochs = 7,200 steps, the x2-budget control's), the retraining should get
# as much of it as the pseudo-labeller can spare: PRE_EPOCHS=2 (default) pretrains 2 epochs
# (1,200 steps) and leaves (12 - PRE)/2 retraining epochs of 1,200 steps (600 source + 600 PPCG
# frames) to the Makefile: x1 long retrains 5 (6,000 steps), x2 1 + 4 (the default split is
# 4 epochs + 1 + 3: x1 long 4,800 steps, x2 1,200 + 3,600). Same data, library and seeds as
# runs/experiment-s$SEED (synthesized there if absent); the control and oracle rows are that run's
# (their budget does not change). Evaluated on the 200 validation frames and on val800_job.sh's
# 800 fresh frames (KITTI easy / moderate / hard on the 200). Resumable: rerun the same command
# (make skips finished stages, training resumes from model.resume/). By default the shared part
# uses both cores, then x1 long and x2 run as two 1-thread lanes pinned to cores 0 and 1; CORE=c
# runs the whole job on core c alone, its rows (ROWS, default "x1-long iter2") one after the
# other, so that two seeds can share the VM.
#   bash docs/results/exp600/short_pretrain_job.sh       # from the directory holding runs/
#   SEED=1 CORE=0 bash docs/results/exp600/short_pretrain_job.sh
set -euo pipefail
SEED=${SEED:-0}; PRE=${PRE_EPOCHS:-2}; TOTAL=12; CORE=${CORE:-}; ROWS=${ROWS:-x1-long iter2}
RE=$(( (TOTAL - PRE) / 2 ))  # retraining epochs, each 2 x 600 frames
[ $(( PRE + 2 * RE )) -eq $TOTAL ] && [ $RE -ge 2 ] || { echo "PRE_EPOCHS must be even, <= 8" >&2; exit 2; }
HERE=$(cd "$(dirname "$0")" && pwd)
MAKEFILE=${MAKEFILE:-$HERE/../../../Makefile}
D=${DALI:-.venv/bin/dali}
R=runs/experiment-s$SEED
V=$R/variants/pretrain$PRE
COMMON=(SEED=$SEED SOURCE_SENSOR=waymo FRAMES=600 VAL_FRAMES=200)
ALL=(taskset -c ${CORE:-0-$(( $(nproc) - 1 ))}); WORKERS=$([ -n "$CORE" ] && echo 1 || echo 2)
"${ALL[@]}" make -f "$MAKEFILE" RUN=$R "${COMMON[@]}" SYNTH_WORKERS=$WORKERS $R/data/source/manifest.json \
    $R/data/target/manifest.json $R/data/target_val/manifest.json $R/library/manifest.json
mkdir -p $V
for shared in data library; do ln -sfn ../../$shared $V/$shared; done
M=(make -f "$MAKEFILE" RUN=$V "${COMMON[@]}" EPOCHS=$PRE RETRAIN_EPOCHS=2 RETRAIN_EPOCHS_1=1 RETRAIN_EPOCHS_2=$(( RE - 1 )))
"${ALL[@]}" "${M[@]}" "TRAIN_FLAGS=--threads $WORKERS" WORKERS=$WORKERS $V/iter1/rc/manifest.json \
    $V/iter1/cf/manifest.json $V/iter0/eval_ptsn/manifest.json
source "$HERE/eval_row.sh"
O=runs/val800/experiment-s$SEED/pretrain$PRE
val800_eval() {  # NAME MODEL PTSN CORE: MODEL at PTSN's scale on the 800 fresh frames
  D="taskset -c $4 $D" val800_row $V/$2 $O/$1 --scale-from $V/$3
}
row() {  # GOAL CORE: one row through the Makefile, then on the 800 frames
  taskset -c $2 "${M[@]}" "TRAIN_FLAGS=--threads 1" WORKERS=1 $1
  case $1 in
    x1-long) val800_eval x1_long x1_long/model x1_long/ptsn $2;;
    iter2) val800_eval x2 iter2/model iter3/ptsn $2;;
  esac
}
if [ -n "$CORE" ]; then
  for goal in $ROWS; do row $goal $CORE; done
else
  set -- $ROWS
  row $1 0 & pids=($!)
  [ -z "${2:-}" ] || { row $2 1 & pids+=($!); }
  for pid in "${pids[@]}"; do wait $pid; done
fi
val800_eval iter0_ptsn iter0/model iter1/ptsn ${CORE:-0}
for row in iter0/eval_ptsn x1_long/eval iter2/eval; do  # KITTI easy / moderate / hard, 200 frames
  [ ! -f $V/$row/predictions.parquet ] || kitti_row $V/$row
done
