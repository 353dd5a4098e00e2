#!/usr/bin/env bash
# #26 on one GPU: does a longer minimum before an early stop remove the misses of copies that stop very early?
# Pool jobs (K = 16, 64 fresh secret 32-bit messages each) with the window998 setting and `min_steps=384` (instead of
# the preset's 96), on two lego models trained here for 60 s with train seeds not used before (2 and 3), one job
# after another (the GPU and host to each job alone):
#
#   bash benchmarks/pool_minsteps.sh WORKDIR LEGO_DIR
#
# Set-up, progress and polling as in benchmarks/gpu_round.sh (its header).
set -uo pipefail
W=${1:?WORKDIR}
LEGO=${2:?LEGO_DIR}
. benchmarks/steps.sh
STOP="quality,confirm=0.998,accuracy_window=32,min_steps=384"
for seed in 2 3; do
  fp="$W/fp$seed"
  step "prepare$seed" python3 benchmarks/fingerprint_multi_gpu.py prepare --data "$LEGO" --workdir "$fp" --train-seed "$seed"
  photos=$(python3 -c "import json, sys; print(json.load(open(sys.argv[1]))['photos'])" "$fp/prepare.json")
  step "job$seed" python3 benchmarks/fingerprint_throughput.py --device cuda --out "$W" --scene lego --model "$fp/model" \
    --data "$photos" --budget-s 900 --setting "k=16 n=64 stop=$STOP" --tag "fingerprint_lego_h200_minsteps_r10_seed$seed"
done
log "round done"
