#!/usr/bin/env bash
# #26 on a host with 2 GPUs (2026-11-27, eighth session): does checking a copy on validation views (poses between the
# embedding cameras, never trained on; EarlyStop.validation) remove the copies that the embedding views confirm but
# the held-out views reject?
#
#   bash benchmarks/pool_validation.sh WORKDIR LEGO_DIR [RECIPIENTS]
#
# GPU 0 trains lego model C (60 s, seed 2); then, at the same time on that model, one pool job each (K = 16,
# RECIPIENTS fresh secret messages, default 48): GPU 0 the eighth round's best setting without validation views,
# GPU 1 the same with 16 validation views at >= 99.5 % bits.
# Progress in WORKDIR/progress.log ("round done" at the end); set-up and polling as in benchmarks/gpu_round.sh.
set -uo pipefail
W=${1:?WORKDIR}
LEGO=${2:?LEGO_DIR}
N=${3:-48}
. benchmarks/steps.sh
BASE="quality,confirm=0.998,accuracy_window=32"
SETTINGS=("$BASE" "$BASE,validation=16,validation_bits=0.995")
step prepare_c env CUDA_VISIBLE_DEVICES=0 python3 benchmarks/fingerprint_multi_gpu.py prepare --data "$LEGO" \
  --workdir "$W/fpC" --train-seed 2
P=$(python3 -c "import json, sys; print(json.load(open(sys.argv[1]))['photos'])" "$W/fpC/prepare.json")
pids=()
for g in 0 1; do
  step "val_$g" env CUDA_VISIBLE_DEVICES=$g python3 benchmarks/fingerprint_throughput.py --device cuda --out "$W" \
    --scene lego --model "$W/fpC/model" --data "$P" --budget-s 900 --setting "k=16 n=$N stop=${SETTINGS[$g]}" \
    --tag "val_$g" &
  pids+=($!)
done
wait "${pids[@]}"
log "round done"
