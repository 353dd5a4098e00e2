#!/usr/bin/env bash
# One round of GPU work on a host with 4 GPUs (2026-11-27, seventh session; issues #26 #27, and the whole suite
# for every Python change that touches renders since the last whole GPU suite):
#
#   bash benchmarks/gpu_round.sh WORKDIR LEGO_DIR
#
# Phase 1, at the same time:
#   GPU 3: the whole test suite with this CUDA build;
#   GPU 0: fingerprint_multi_gpu.py prepare (lego trained 60 s), then pool_round.sh's "host" step on that model
#          (#26: the loss A/B, a 30-step profile with the device's busy share and a trace, the quality preset on
#          32 recipients and the throughput preset on 16, K = 16, one process), then the quality preset on 32
#          fresh recipients again (a second sample of the same setting);
#   GPUs 1-2, once the model exists: `gsw fingerprint` through Ray on 2 GPUs (1, 2), then on 1 GPU (1) (#27), with
#          the quality preset (fingerprint_multi_gpu.py's default).
# Phase 2, the host otherwise idle: `gsw scan` over 10,000 files on 1 GPU (in one process and on Ray), 2 and 4
#   GPUs (Ray Data); `gsw fingerprint` through Ray on 4 GPUs; the copies of the 1-, 2- and 4-GPU runs compared.
#
# Progress in WORKDIR/progress.log, each step's output in WORKDIR/<step>.log, results WORKDIR/*.json / *.txt.
#
# Set-up on an offline GPU machine (torch preinstalled; .whl = kornia, kornia_rs, scikit_build_core, pybind11,
# pathspec wheels, .whl-ray = benchmarks/ray_bundle.sh's bundle, build/gpu/lego = the WebP photos of power_lego.py
# --pack-webp; the tracked tree is ~45 MiB of the 64-MiB transfer limit, so .whl-ray travels in its own call):
#   sh .whl-ray/INSTALL.sh && python3 -m pip install -q --no-deps --target /tmp/site2 .whl/*.whl
#   export PYTHONPATH=/tmp/site:/tmp/site2 PATH=/tmp/site2/bin:/tmp/site/bin:$PATH
#   TORCH_CUDA_ARCH_LIST=9.0 GSW_WITH_CUDA=ON python3 -m pip install -q --no-build-isolation --no-deps -e .
# then start this script with setsid nohup ... & and poll WORKDIR/progress.log without gaps (an idle machine is
# taken back after 30 s). Every device call copies the working tree afresh and the editable install imports gsw
# from it: a suite started in one call and still collecting when the next call starts fails with missing files
# (2026-11-27: 37 collection errors). Start this script in the last call that carries files, then poll with long
# calls (few re-copies).
set -uo pipefail
W=${1:?WORKDIR}
LEGO=${2:?LEGO_DIR}
. benchmarks/steps.sh
on_gpu() { local g=$1; shift; CUDA_VISIBLE_DEVICES=$g "$@"; }
FP="python3 benchmarks/fingerprint_multi_gpu.py"

step suite on_gpu 3 python3 -m pytest -q -p no:cacheprovider -rfE tests &
suite=$!
step prepare on_gpu 0 $FP prepare --data "$LEGO" --workdir "$W/fp"
PHOTOS=$(python3 -c "import json, sys; print(json.load(open(sys.argv[1]))['photos'])" "$W/fp/prepare.json")
(on_gpu 0 bash benchmarks/pool_round.sh "$W" "$LEGO" host
 step tp_repeat on_gpu 0 python3 benchmarks/fingerprint_throughput.py --device cuda --out "$W" --scene lego \
   --model "$W/fp/model" --data "$PHOTOS" --budget-s 900 --setting "k=16 n=32 stop=quality" --tag lego_repeat) &
pool=$!
step fingerprint_2 $FP run --gpus 2 --first-gpu 1 --workdir "$W/fp"
step fingerprint_1 $FP run --gpus 1 --first-gpu 1 --workdir "$W/fp"
wait $pool
log "pool finished"
while kill -0 "$suite" 2>/dev/null; do sleep 2; done
log "suite finished"
SC=(python3 benchmarks/scan_throughput.py --images 10000 --model "$W/fp/model" --marks 64 --device cuda --readers 8
    --workdir "$W/scan10k")
step scan_1 "${SC[@]}" --gpus 1 --modes batched,ray --out "$W/scan_cuda_1gpu.json"
for g in 2 4; do
  step "scan_$g" "${SC[@]}" --gpus "$g" --modes ray --out "$W/scan_cuda_${g}gpu.json"
done
step fingerprint_4 $FP run --gpus 4 --workdir "$W/fp"
step compare $FP compare --runs 1 2 4 --workdir "$W/fp" --out "$W/fingerprint_multi_gpu.json"
log "round done"
