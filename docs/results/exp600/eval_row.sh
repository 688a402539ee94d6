# Sourced by the session-23 jobs (target_share_job.sh, oracle_budget_job.sh,
# oracle_restart_job.sh): evaluate_row MODEL OUT VAL800_OUT SCALE_OPTION...
# evaluates MODEL at SCALE_OPTION (e.g. --scale 1.0, or --scale-from PTSN_DIR) on RUN R's 200
# validation frames (range protocol, front region -> OUT; KITTI easy/moderate/hard ->
# OUT/metrics_kitti.json) and on val800_job.sh's 800 fresh frames of SEED (-> VAL800_OUT).
# Needs D (dali), R (RUN) and SEED set; every output is an artifact, skipped when up to date.
evaluate_row() {
  local model=$1 out=$2 val800_out=$3; shift 3
  local p="--protocol range --front-only --iou 0.7 --iou 0.5 --size-score-min 0.3"
  $D eval --model $model --data $R/data/target_val "$@" $p --workers 1 --no-progress --out $out
  $D eval --pred $out/predictions.parquet --gt $R/data/target_val --protocol kitti \
      --iou 0.7 --iou 0.5 --size-score-min 0.3 --out $out/metrics_kitti.json
  $D eval --model $model --data runs/val800/data-s$SEED "$@" $p --workers 1 --no-progress \
      --out $val800_out
}
