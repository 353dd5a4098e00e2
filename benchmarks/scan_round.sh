#!/usr/bin/env bash
# `gsw scan` on 1, 2 and 4 GPUs of one host (#27), after the readers stopped copying (commit of this file):
#
#   bash benchmarks/scan_round.sh WORKDIR
#
# 10,000 files of the built-in scene at 800x800 (16 renders, the rest JPEG re-encodings), 64 marks: on 1 GPU in one
# process with the new readers and the old (batched / batched-f32), with the decoder replaced by random logits
# (host-only: what the host side sustains), and on Ray; on 2 and 4 GPUs on Ray (Ray Data).
# Set-up and polling as in benchmarks/gpu_round.sh (its header).
set -uo pipefail
W=${1:?WORKDIR}
. benchmarks/steps.sh
SC=(python3 benchmarks/scan_throughput.py --images 10000 --size 800 --marks 64 --device cuda --readers 8
    --workdir "$W/scan10k")
step scan_1 "${SC[@]}" --gpus 1 --modes batched,batched-f32,host-only,ray --out "$W/scan_cuda_1gpu.json"
for g in 2 4; do
  step "scan_$g" "${SC[@]}" --gpus "$g" --modes ray --out "$W/scan_cuda_${g}gpu.json"
done
log "round done"
