#!/bin/bash
# a later run (the benchmark's target), seed 0 unless SEED: the paired bootstrap (`dali compare`, 400 draws,
# R40 and R400) of the 12,000-step rows on the 800 fresh frames, against the control: x1 long and
# the control's rows of budget_job.sh, x2 of x2_long_job.sh, and the diagnostics that read target
# labels, PPCG from the true boxes (truth_job.sh RETRAIN_EPOCHS=4) and the raw target frames with
# all true labels at its ŝ and at s = 1 (target_share_job.sh SET=rawtrue MIX=1:1 EPOCHS=8; also
# MIX=1:7 EPOCHS=2, with and without INIT_FROM=scratch), and x1 long with less of the source
# on iteration 1's PPCG frames (SET=ppcg MIX=1:3 EPOCHS=4, MIX=1:7 EPOCHS=2; label-free) and on
# the true boxes' and the found cars' pseudo boxes' (SET=truth-matched|pseudo-matched MIX=1:7
# EPOCHS=2), and the raw target frames with iteration 1's pseudo boxes instead of
# PPCG (SET=rawpseudo MIX=1:7 EPOCHS=2) and PPCG from `pseudo-label --tta` boxes (LABELS=tta
# SET=ppcg MIX=1:7 EPOCHS=2), both label-free, and PPCG with `--occlusion` (PPCG=occ
# SET=ppcg, MIX=1:7 EPOCHS=2 and MIX=1:1 EPOCHS=8) and from `pseudo-label --fit-ground` boxes
# (LABELS=ground, with and without PPCG=occ, 1:7), and with the boxes scored 0.3-0.6
# as ignore regions (LABELS=ignore SET=ppcg, MIX=1:7 EPOCHS=2 and MIX=1:1 EPOCHS=8) and with the
# 0.6 cut alone (LABELS=cut06, 1:7), each where finished. ONLY (an extended regex)
# keeps the rows whose names match it, the control always (TAG names the output then, e.g.
# ONLY='^x1 long$|PPCG 1:7|occlusion' TAG=compare29).
# Writes runs/val800/experiment-s$SEED/budget-re$RE/${TAG:-compare27}_r{40,400}.json.
#   taskset -c 0 bash docs/results/exp600/budget_compare.sh     # from the directory holding runs/
set -euo pipefail
SEED=${SEED:-0}; RE=${RETRAIN_EPOCHS:-4}; D=${DALI:-.venv/bin/dali}
O=runs/val800/experiment-s$SEED
rows=()  # NAME=DIR under O; NAME holds no '='
for row in "control=budget-re$RE/control" "x1 long=budget-re$RE/x1_long" "x2=x2long-re$RE/iter2" \
    "x1 long, true boxes=x1long-truth-matched-re$RE" "x1 long, raw target=x1long-rawtrue-mix11-ep$(( 2 * RE ))" \
    "x1 long, raw target at s 1=x1long-rawtrue-mix11-ep$(( 2 * RE ))-s1" \
    "raw target 1:7=x1long-rawtrue-mix17-ep$(( RE / 2 ))" "raw target 1:7 at s 1=x1long-rawtrue-mix17-ep$(( RE / 2 ))-s1" \
    "raw target 1:7 scratch=x1long-rawtrue-mix17-scratch-ep$(( RE / 2 ))" \
    "raw target 1:7 scratch at s 1=x1long-rawtrue-mix17-scratch-ep$(( RE / 2 ))-s1" \
    "true boxes 1:7=x1long-truth-matched-mix17-ep$(( RE / 2 ))" \
    "found pseudo boxes 1:7=x1long-pseudo-matched-mix17-ep$(( RE / 2 ))" \
    "x1 long, PPCG 1:3=x1long-ppcg-mix13-ep$RE" "x1 long, PPCG 1:7=x1long-ppcg-mix17-ep$(( RE / 2 ))" \
    "raw target, pseudo boxes 1:7=x1long-rawpseudo-mix17-ep$(( RE / 2 ))" \
    "PPCG from --tta boxes 1:7=x1long-ppcg-tta-mix17-ep$(( RE / 2 ))" \
    "PPCG with occlusion 1:7=x1long-ppcg-occ-mix17-ep$(( RE / 2 ))" \
    "x1 long, PPCG with occlusion=x1long-ppcg-occ-mix11-ep$(( 2 * RE ))" \
    "PPCG from --fit-ground boxes 1:7=x1long-ppcg-ground-mix17-ep$(( RE / 2 ))" \
    "PPCG from --fit-ground boxes with occlusion 1:7=x1long-ppcg-ground-occ-mix17-ep$(( RE / 2 ))" \
    "ignore regions 1:7=x1long-ppcg-ignore-mix17-ep$(( RE / 2 ))" \
    "x1 long, ignore regions=x1long-ppcg-ignore-mix11-ep$(( 2 * RE ))" \
    "cut 0.6 without ignore regions 1:7=x1long-ppcg-cut06-mix17-ep$(( RE / 2 ))" \
    "oracle=budget-re$RE/oracle"; do
  name=${row%%=*}
  [ -z "${ONLY:-}" ] || [ "$name" = control ] || [[ "$name" =~ $ONLY ]] || continue
  [ -f "$O/${row#*=}/predictions.parquet" ] && rows+=(--pred "$name=$O/${row#*=}/predictions.parquet")
done
for positions in 40 400; do
  $D compare "${rows[@]}" --gt runs/val800/data-s$SEED --protocol range --front-only --iou 0.7 \
      --recall-positions $positions --samples 400 --seed 0 --no-progress \
      --out $O/budget-re$RE/${TAG:-compare27}_r$positions.json
done
