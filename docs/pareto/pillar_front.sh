#!/bin/bash
# issue 21: detector pillar size front. Oracle (target labels) of demo3-s0, 10 epochs (480 frames), 2 threads, idle machine.
set -e
D=.venv/bin/dali; R=runs/demo3-s0; F=runs/pillar_front/seed${SEED:-0}
mkdir -p $F
for p in 0.32 0.24 0.40; do
  echo "{\"pillar_m\": $p}" > $F/config_$p.json
  uptime
  $D pretrain --source $R/data/target --epochs 10 --seed ${SEED:-0} --threads 2 --quiet --detector-config $F/config_$p.json --out $F/p$p/model
  uptime
  $D eval --model $F/p$p/model --data $R/data/target_val --scale 1.0 --protocol range --front-only --iou 0.7 --iou 0.5 --size-score-min 0.3 --workers 1 --out $F/p$p/eval
  $D eval --pred $F/p$p/eval/predictions.parquet --gt $R/data/target_val --protocol kitti --iou 0.7 --size-score-min 0.3 --out $F/p$p/eval/metrics_kitti.json
done
