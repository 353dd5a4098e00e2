#!/usr/bin/env bash
# #26 on one GPU (2026-11-28, seventeenth session): `EarlyStop.redraw` measured on fresh models and messages, one job
# after another with the GPU and host to each alone:
#
#   bash benchmarks/redraw_round.sh WORKDIR LEGO_DIR
#
# lego trained 60 s with train seed 4 and one pool job on it; the built-in scene (256x256, 24 embedding / 8 held-out
# views, 64-epoch cap); lego trained 60 s with train seed 5 and one pool job on it. Each job: K = 16, 64 fresh secret
# 32-bit messages, `--early-stop careful,redraw=2` (the redraw threshold, 0.995 on the embedding views, was read off
# the earlier rounds' jobs; these models and messages are new).
# Set-up, progress and polling as in benchmarks/gpu_round.sh (its header); carry .whl (without gsplat) and
# build/gpu/lego in one call (64-MiB transfer limit).
set -uo pipefail
W=${1:?WORKDIR}
LEGO=${2:?LEGO_DIR}
. benchmarks/steps.sh
STOP="careful,redraw=2"
lego_job() {  # SEED
  local seed=$1 fp="$W/fp$1"
  step "prepare$seed" python3 benchmarks/fingerprint_multi_gpu.py prepare --data "$LEGO" --workdir "$fp" --train-seed "$seed"
  local photos
  photos=$(python3 -c "import json, sys; print(json.load(open(sys.argv[1]))['photos'])" "$fp/prepare.json")
  step "job$seed" python3 benchmarks/fingerprint_throughput.py --device cuda --out "$W" --scene lego --model "$fp/model" \
    --data "$photos" --budget-s 900 --setting "k=16 n=64 stop=$STOP" --tag "fingerprint_lego_h200_redraw_r17_seed$seed"
}
lego_job 4
step builtin python3 benchmarks/fingerprint_throughput.py --device cuda --out "$W" --scene builtin --size 256 \
  --views 24 --held-out 8 --budget-s 900 --setting "k=16 n=64 epochs=64 stop=$STOP" \
  --tag "fingerprint_builtin_h200_redraw_r17"
lego_job 5
log "round done"
