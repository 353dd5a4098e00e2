#!/usr/bin/env bash
# `gsw scan` on Ray Data with one call per worker (RAY_SOURCES_PER_CALL 64, commit of this file) on 1 and 4 GPUs
# of one host (#27): 10,000 files of the built-in scene at 800x800 (16 renders as PNG, the rest JPEG re-encodings),
# 64 marks, 8 readers, each call's timeline in the JSONs. Set-up and polling as in benchmarks/gpu_round.sh.
#
#   bash benchmarks/scan_calls.sh WORKDIR
set -uo pipefail
W=${1:?WORKDIR}
. benchmarks/steps.sh
SC=(python3 benchmarks/scan_throughput.py --images 10000 --size 800 --marks 64 --device cuda --readers 8
    --workdir "$W/scan10k")
step scan_calls_1 "${SC[@]}" --gpus 1 --modes ray --out "$W/scan_calls_1gpu.json"
step scan_calls_4 "${SC[@]}" --gpus 4 --modes ray --out "$W/scan_calls_4gpu.json"
log "round done"
