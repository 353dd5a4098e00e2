#!/usr/bin/env bash
# #26 on one GPU: do hard messages stay hard when they start over? Pool jobs (K = 16, 48 fresh secret 32-bit
# messages each) with the window998 setting plus `restart=1` (a copy that fails the confirmation on the embedding
# views at its last cap starts over with a new view order; EarlyStop.restart), on two lego models trained here for
# 60 s (train seeds 0 and 1), one job after another (the GPU and host to each job alone):
#
#   bash benchmarks/pool_restart.sh WORKDIR LEGO_DIR
#
# Set-up, progress and polling as in benchmarks/gpu_round.sh (its header).
set -uo pipefail
W=${1:?WORKDIR}
LEGO=${2:?LEGO_DIR}
. benchmarks/steps.sh
STOP="quality,confirm=0.998,accuracy_window=32,restart=1"
job() {  # job NAME SEED: the pool on the model of train seed SEED (trained first if missing)
  local fp="$W/fp$2"
  [ -f "$fp/prepare.json" ] || step "prepare$2" python3 benchmarks/fingerprint_multi_gpu.py prepare --data "$LEGO" \
    --workdir "$fp" --train-seed "$2"
  local photos
  photos=$(python3 -c "import json, sys; print(json.load(open(sys.argv[1]))['photos'])" "$fp/prepare.json")
  step "$1" python3 benchmarks/fingerprint_throughput.py --device cuda --out "$W" --scene lego --model "$fp/model" \
    --data "$photos" --budget-s 900 --setting "k=16 n=48 stop=$STOP" --tag "lego_restart_$1"
}
job job0 0
job job1 1
job job2 0
log "round done"
