#!/usr/bin/env bash
# The next round after the twenty-eighth session's (BENCHMARKS.md "Twentieth GPU round", 9o), on one host with 2 GPUs:
#
#   setsid nohup bash benchmarks/round_r29.sh WORKDIR LEGO_DIR >/dev/null 2>&1 &
#
# From a snapshot of the tree in WORKDIR/src, built there for the GPU (benchmarks/steps.sh):
# GPU 0 (#26, `gsw fingerprint`'s defaults since 2026-11-29: SH rest frozen, squared-error term, no FGD, `quality`):
#   lego trained ~60 s (fingerprint_multi_gpu.py prepare); then fingerprint_throughput.py --exports on that model, 64
#   copies with `quality` (never run at 64 under this recipe), then the built-in scene at 256 px, 64 copies of
#   `probed` with probe_bits=0.995 once more (64 of 64 at 3,419 per GPU-hour in the twentieth round's last job).
# GPU 1: the whole test suite with the CUDA build; then (#23) 64 bits on that lego model at 16 and 24 epochs, 3 seeds,
#   clean reads (8 epochs: 93.6 % at 36.86 dB; on the CPU the steps bought more than the message weight, 9o), and the
#   bare SH-0 model at 64 epochs without and with render-size sampling (32 epochs with it: 98.7 / 92.8 % at
#   35.4 / 35.7 dB).
# Needs kornia in /tmp/site2 (the .whl wheels). Progress in WORKDIR/progress.log ("round done" at the end).
set -uo pipefail
W=$(mkdir -p "${1:?WORKDIR}" && cd "$1" && pwd)
LEGO=$(cd "${2:?LEGO_DIR}" && pwd)
. benchmarks/steps.sh
snapshot_build || exit 1
TP=(python3 benchmarks/fingerprint_throughput.py --device cuda --out "$W" --exports --budget-s 3000)
gpu1() {
  export CUDA_VISIBLE_DEVICES=1
  step suite python3 -m pytest -q -p no:cacheprovider -rfE tests
  while [ ! -f "$W/fp/prepare.json" ]; do sleep 5; done
  RW=(python3 benchmarks/robust_wild.py --scene lego --model "$W/fp/model" --data "$W/fp/lego_png" --device cuda
      --out "$W" --methods --seeds 0 1 2)
  step rw_bits64 "${RW[@]}" --bits 64 --variant e16 default '{"epochs":16}' --variant e24 default '{"epochs":24}' \
    --image-attacks --model-attacks --sizes --tag lego_bits64_r29
  step rw_bare "${RW[@]}" --methods default --seeds 0 --bare --epochs 64 \
    --variant scales default '{"render_scales":[0.5,1.0]}' --tag lego_bare_r29
}
gpu1 &
g1=$!
export CUDA_VISIBLE_DEVICES=0
step prepare python3 benchmarks/fingerprint_multi_gpu.py prepare --data "$LEGO" --workdir "$W/fp" --recipients 4
step tp_lego "${TP[@]}" --scene lego --model "$W/fp/model" --data "$W/fp/lego_png" --setting "k=16 n=64 stop=quality" \
  --tag lego_r29
step tp_builtin "${TP[@]}" --scene builtin --size 256 --setting "k=16 n=64 epochs=64 stop=probed,probe_bits=0.995" \
  --tag builtin_r29
wait $g1
log "round done"
