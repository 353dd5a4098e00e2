#!/usr/bin/env bash
# #26 on a host with 2 GPUs (written 2026-11-27, eighth session; not yet run): are hard messages predictable from
# the input model's renders, and does a longer extension (no weight boost) bring them to >= 99 % held-out?
#
#   bash benchmarks/pool_hard.sh WORKDIR LEGO_DIR [RECIPIENTS]
#
# GPU 0 trains lego model D (60 s, seed 3); then, at the same time on that model, one pool job each (K = 16,
# RECIPIENTS fresh secret messages, default 48): GPU 0 `quality,confirm=0.998,accuracy_window=32` (the eighth round's
# best), GPU 1 the same with extend=1.5 (a copy unconfirmed at the cap may go on for 1.5 x the cap). Every row of the
# JSONs carries the message's head start on the input model's renders (fingerprint_throughput.head_start).
# Progress in WORKDIR/progress.log ("round done" at the end); set-up and polling as in benchmarks/gpu_round.sh.
set -uo pipefail
W=${1:?WORKDIR}
LEGO=${2:?LEGO_DIR}
N=${3:-48}
. benchmarks/steps.sh
BASE="quality,confirm=0.998,accuracy_window=32"
SETTINGS=("$BASE" "$BASE,extend=1.5")
step prepare_d env CUDA_VISIBLE_DEVICES=0 python3 benchmarks/fingerprint_multi_gpu.py prepare --data "$LEGO" \
  --workdir "$W/fpD" --train-seed 3
P=$(python3 -c "import json, sys; print(json.load(open(sys.argv[1]))['photos'])" "$W/fpD/prepare.json")
pids=()
for g in 0 1; do
  step "hard_$g" env CUDA_VISIBLE_DEVICES=$g python3 benchmarks/fingerprint_throughput.py --device cuda --out "$W" \
    --scene lego --model "$W/fpD/model" --data "$P" --budget-s 900 --setting "k=16 n=$N stop=${SETTINGS[$g]}" \
    --tag "hard_$g" &
  pids+=($!)
done
wait "${pids[@]}"
log "round done"
