#!/usr/bin/env bash
# GPU rounds on one host with 2 GPUs (issues #26, #23 and the whole suite), from the twenty-eighth session on:
#
#   setsid nohup bash benchmarks/round_2gpu.sh ROUND WORKDIR LEGO_DIR >/dev/null 2>&1 &
#
# From a snapshot of the tree in WORKDIR/src, built there for the GPU (benchmarks/steps.sh). Both rounds train lego
# ~60 s on GPU 0 (fingerprint_multi_gpu.py prepare) and run the whole test suite with the CUDA build on GPU 1, then:
# r28 (BENCHMARKS.md "Twentieth GPU round", 9o):
#   GPU 0: fingerprint_throughput.py --exports on that model: 64 copies of `assured --mse 35 --no-fgd` with the SH rest
#   frozen (the pool's default then), 32 of the same with `quality`, 32 with the paper's recipe (`freeze=none`).
#   GPU 1: 48 and 64 bits under the library default `EmbedConfig()`, 3 seeds, clean reads; the bare SH-0 model at 32
#   epochs with and without render-size sampling; the built-in scene at 256 px, 64 copies of `assured`; `gsw scan`'s
#   rate over held-out lego renders against 64 marks (GPU and the host's CPU).
# r29 (next; `gsw fingerprint`'s defaults since 2026-11-29: SH rest frozen, squared-error term, no FGD, `quality`):
#   GPU 0: 64 lego copies with `quality` (never run at 64 under this recipe), then the built-in scene, 64 copies of
#   `probed,probe_bits=0.995` once more (64 of 64 at 3,419 per GPU-hour in the twentieth round's last job).
#   GPU 1: 64 bits at 16 and 24 epochs, 3 seeds, clean reads (8 epochs: 93.6 % at 36.86 dB; on the CPU the steps
#   bought more than the message weight, 9o); the bare SH-0 model at 64 epochs without and with render-size sampling.
# Needs kornia in /tmp/site2 (the .whl wheels). Progress in WORKDIR/progress.log ("round done" at the end).
set -uo pipefail
ROUND=${1:?ROUND (r28 or r29)}
W=$(mkdir -p "${2:?WORKDIR}" && cd "$2" && pwd)
LEGO=$(cd "${3:?LEGO_DIR}" && pwd)
case $ROUND in r28|r29) ;; *) echo "unknown round $ROUND" >&2; exit 2 ;; esac
. benchmarks/steps.sh
snapshot_build || exit 1
TP=(python3 benchmarks/fingerprint_throughput.py --device cuda --out "$W" --exports --budget-s 3000)
AS="stop=assured l1=0 mse=35 fgd=0"
gpu1() {
  export CUDA_VISIBLE_DEVICES=1
  step suite python3 -m pytest -q -p no:cacheprovider -rfE tests
  while [ ! -f "$W/fp/prepare.json" ]; do sleep 5; done
  RW=(python3 benchmarks/robust_wild.py --scene lego --model "$W/fp/model" --data "$W/fp/lego_png" --device cuda
      --out "$W" --methods default --seeds 0 1 2)
  NONE=(--image-attacks --model-attacks --sizes)
  SCALES=(--variant scales default '{"render_scales":[0.5,1.0]}')
  if [ "$ROUND" = r28 ]; then
    step rw_bits "${RW[@]}" --bits 48 64 "${NONE[@]}" --tag lego_bits_r28
    step rw_bare "${RW[@]}" --seeds 0 --bare --epochs 32 "${SCALES[@]}" --tag lego_bare_r28
    step tp_builtin "${TP[@]}" --scene builtin --size 256 --setting "k=16 n=64 epochs=64 $AS" --tag builtin_r28
    step scan python3 benchmarks/fingerprint_throughput.py --device cuda --out "$W" --scene lego \
      --model "$W/fp/model" --data "$W/fp/lego_png" --scan-only 64 --scan-images 256 --scan-cpu-images 32 \
      --tag lego_scan_r28
  else
    step rw_bits64 "${RW[@]}" --methods --bits 64 --variant e16 default '{"epochs":16}' \
      --variant e24 default '{"epochs":24}' "${NONE[@]}" --tag lego_bits64_r29
    step rw_bare "${RW[@]}" --seeds 0 --bare --epochs 64 "${SCALES[@]}" --tag lego_bare_r29
  fi
}
gpu1 &
g1=$!
export CUDA_VISIBLE_DEVICES=0
step prepare python3 benchmarks/fingerprint_multi_gpu.py prepare --data "$LEGO" --workdir "$W/fp" --recipients 4
LM=(--scene lego --model "$W/fp/model" --data "$W/fp/lego_png")
if [ "$ROUND" = r28 ]; then
  step tp_lego "${TP[@]}" "${LM[@]}" --setting "k=16 n=64 $AS" --setting "k=16 n=32 stop=quality l1=0 mse=35 fgd=0" \
    --setting "k=16 n=32 $AS freeze=none" --tag lego_r28
else
  step tp_lego "${TP[@]}" "${LM[@]}" --setting "k=16 n=64 stop=quality" --tag lego_r29
  step tp_builtin "${TP[@]}" --scene builtin --size 256 --setting "k=16 n=64 epochs=64 stop=probed,probe_bits=0.995" \
    --tag builtin_r29
fi
wait $g1
log "round done"
