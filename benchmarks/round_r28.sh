#!/usr/bin/env bash
# The twenty-eighth session's round on one host with 2 GPUs (issues #26, #23 and the whole suite):
#
#   setsid nohup bash benchmarks/round_r28.sh WORKDIR LEGO_DIR >/dev/null 2>&1 &
#
# From a snapshot of the tree in WORKDIR/src, built there for the GPU (benchmarks/steps.sh):
# GPU 0 (#26, the pool's new default on lego 800x800): lego trained ~60 s (fingerprint_multi_gpu.py prepare), then
#   fingerprint_throughput.py --exports on that model: 64 copies of `assured --mse 35 --no-fgd` with the SH rest
#   frozen (the pool's default), 32 of the same with the `quality` preset, and 32 with the paper's recipe
#   (`freeze=none`) as the control, every copy read on the held-out views also after SH 0 / .splat / .spz.
# GPU 1: the whole test suite with the CUDA build; then (#23, the library default `EmbedConfig()`) 48 and 64 bits on
#   that lego model, 3 seeds, clean reads only; the bare SH-0 model at 32 epochs with and without render-size
#   sampling; then (#26) the built-in scene at 256 px: 64 copies of `assured --mse 35 --no-fgd` with --exports, and
#   `gsw scan`'s rate over held-out renders of the lego model against 64 marks (GPU, and the host's CPU).
# Needs kornia in /tmp/site2 (the .whl wheels). Progress in WORKDIR/progress.log ("round done" at the end).
set -uo pipefail
W=$(mkdir -p "${1:?WORKDIR}" && cd "$1" && pwd)
LEGO=$(cd "${2:?LEGO_DIR}" && pwd)
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
  step rw_bits "${RW[@]}" --bits 48 64 --image-attacks --model-attacks --sizes --tag lego_bits_r28
  step rw_bare "${RW[@]}" --seeds 0 --bare --epochs 32 --variant scales default '{"render_scales":[0.5,1.0]}' \
    --tag lego_bare_r28
  step tp_builtin "${TP[@]}" --scene builtin --size 256 --setting "k=16 n=64 epochs=64 $AS" --tag builtin_r28
  step scan python3 benchmarks/fingerprint_throughput.py --device cuda --out "$W" --scene lego --model "$W/fp/model" \
    --data "$W/fp/lego_png" --scan-only 64 --scan-images 256 --scan-cpu-images 32 --tag lego_scan_r28
}
gpu1 &
g1=$!
export CUDA_VISIBLE_DEVICES=0
step prepare python3 benchmarks/fingerprint_multi_gpu.py prepare --data "$LEGO" --workdir "$W/fp" --recipients 4
step tp_lego "${TP[@]}" --scene lego --model "$W/fp/model" --data "$W/fp/lego_png" --setting "k=16 n=64 $AS" \
  --setting "k=16 n=32 stop=quality l1=0 mse=35 fgd=0" --setting "k=16 n=32 $AS freeze=none" --tag lego_r28
wait $g1
log "round done"
