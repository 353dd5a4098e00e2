#!/usr/bin/env bash
# The twenty-seventh session's #27 round on one host with 4 GPUs:
#
#   setsid nohup bash benchmarks/multi_gpu_r27.sh WORKDIR LEGO_DIR >/dev/null 2>&1 &
#
# It runs from a snapshot of the tree in WORKDIR/src (every device call copies the working tree afresh; a step
# started in one call must not see the next call's copy), built there for the GPU:
# 1. GPU 3: the whole test suite with that CUDA build, beside GPU 0: lego trained 60 s and 256 recipients'
#    messages (fingerprint_multi_gpu.py prepare). The timed runs start when both have ended: the host to itself.
# 2. Strong scaling, the issue's job: `gsw fingerprint` through Ray, the same 64 recipients on 4, 2 and 1 GPUs;
#    the copies compared with the 1-GPU run's and scored on the held-out views.
# 3. Weak scaling (64 recipients per GPU): the first 256 recipients on 4 GPUs, the first 128 on 2; each compared
#    with the 1-GPU run (its 64 copies bitwise, the rate per GPU).
# Needs kornia in /tmp/site2 (the .whl wheels) and Ray in /tmp/site (.whl-ray/INSTALL.sh). Progress in
# WORKDIR/progress.log ("round done" at the end); poll it without gaps (an idle machine is taken back after 30 s).
set -uo pipefail
W=$(mkdir -p "${1:?WORKDIR}" && cd "$1" && pwd)
LEGO=$(cd "${2:?LEGO_DIR}" && pwd)
mkdir -p "$W/lego" && cp -r "$LEGO"/. "$W/lego"/
. benchmarks/steps.sh
snapshot_build || exit 1
step suite env CUDA_VISIBLE_DEVICES=3 python3 -m pytest -q -p no:cacheprovider -rfE tests &
suite=$!
step prepare env CUDA_VISIBLE_DEVICES=0 python3 benchmarks/fingerprint_multi_gpu.py prepare --data "$W/lego" \
  --workdir "$W/fp" --recipients 256
wait $suite
FP=(python3 benchmarks/fingerprint_multi_gpu.py run --workdir "$W/fp")
CMP=(python3 benchmarks/fingerprint_multi_gpu.py compare --workdir "$W/fp")
step fp_4 "${FP[@]}" --gpus 4 --limit 64 --tag 4
step fp_2 "${FP[@]}" --gpus 2 --limit 64 --tag 2
step fp_1 "${FP[@]}" --gpus 1 --limit 64 --tag 1
step compare_strong "${CMP[@]}" --runs 1 2 4 --out "$W/fingerprint_strong.json"
step fp_4x256 "${FP[@]}" --gpus 4 --limit 256 --tag 4x256
step compare_weak4 "${CMP[@]}" --runs 1 4x256 --out "$W/fingerprint_weak4.json"
step fp_2x128 "${FP[@]}" --gpus 2 --limit 128 --tag 2x128
step compare_weak2 "${CMP[@]}" --runs 1 2x128 --out "$W/fingerprint_weak2.json"
log "round done"
