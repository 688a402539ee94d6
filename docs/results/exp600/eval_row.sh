# Sourced by the jobs (target_share_job.sh, oracle_budget_job.sh,
# oracle_restart_job.sh, short_pretrain_job.sh, long_retrain_job.sh). Needs D (the dali command,
# e.g. "taskset -c 1 .venv/bin/dali"), R (RUN) and SEED set; every output is an artifact,
# skipped when up to date.
#   evaluate_row MODEL OUT VAL800_OUT SCALE_OPTION...: MODEL at SCALE_OPTION (e.g. --scale 1.0,
#     or --scale-from PTSN_DIR) on R's 200 validation frames (range protocol, front region -> OUT;
#     KITTI -> OUT/metrics_kitti.json) and on val800_job.sh's 800 fresh frames (-> VAL800_OUT)
#   kitti_row EVAL_DIR: KITTI easy / moderate / hard of EVAL_DIR's predictions on the 200 frames
#   val800_row MODEL OUT SCALE_OPTION...: the 800 fresh frames alone (synthesized if absent)
RANGE_PROTOCOL="--protocol range --front-only --iou 0.7 --iou 0.5 --size-score-min 0.3"
kitti_row() {
  $D eval --pred $1/predictions.parquet --gt $R/data/target_val --protocol kitti \
      --iou 0.7 --iou 0.5 --size-score-min 0.3 --out $1/metrics_kitti.json
}
val800_row() {
  local model=$1 out=$2 frames=runs/val800/data-s$SEED; shift 2
  [ -f $frames/manifest.json ] || $D synth --sensor kitti --cars kitti --frames 800 \
      --seed $(( SEED + 5000 )) --executor local --workers 1 --out $frames
  $D eval --model $model --data $frames "$@" $RANGE_PROTOCOL --workers 1 --no-progress --out $out
}
evaluate_row() {
  local model=$1 out=$2 val800_out=$3; shift 3
  $D eval --model $model --data $R/data/target_val "$@" $RANGE_PROTOCOL --workers 1 --no-progress \
      --out $out
  kitti_row $out
  val800_row $model $val800_out "$@"
}
