#!/usr/bin/env bash
# #27 on one host with 4 GPUs, where the twenty-seventh round left it (BENCHMARKS.md, "Nineteenth GPU round"): with 64
# recipients ~21 s of fixed cost per job caps 4 GPUs at ~0.74 of linear, so here the strong scaling of a job long
# enough to amortise it, and what a smaller local Ray cluster saves of that cost:
#
#   setsid nohup bash benchmarks/multi_gpu_long.sh WORKDIR LEGO_DIR >/dev/null 2>&1 &
#
# From a snapshot of the tree built for the GPU (steps.sh's snapshot_build; kornia in /tmp/site2, Ray in /tmp/site):
# 1. Ray's start as shipped and with num_cpus=4 (ray_start.py: Ray prestarts one idle worker per CPU, 64 here);
# 2. lego trained 60 s, RECIPIENTS (default 256) recipients' messages;
# 3. `gsw fingerprint` through Ray with all of them on 4 GPUs, then on 1 GPU (~15 minutes for 256); LOCAL=1 adds
#    the first 64 on 1 GPU in one process (--local: no Ray, one pool refilled across tasks);
# 4. the 4-GPU run compared with the 1-GPU run (strong scaling, copies bitwise).
# About 1,500 s of device time for 256 recipients. Progress in WORKDIR/progress.log ("round done" at the end).
set -uo pipefail
W=$(mkdir -p "${1:?WORKDIR}" && cd "$1" && pwd)
LEGO=$(cd "${2:?LEGO_DIR}" && pwd)
N=${RECIPIENTS:-256}
mkdir -p "$W/lego" && cp -r "$LEGO"/. "$W/lego"/
. benchmarks/steps.sh
snapshot_build || exit 1
step ray_start python3 benchmarks/ray_start.py --workers 4 --device cuda --repeats 2 --env "" --env num_cpus=4 \
  --out "$W/ray_start.json"
step prepare env CUDA_VISIBLE_DEVICES=0 python3 benchmarks/fingerprint_multi_gpu.py prepare --data "$W/lego" \
  --workdir "$W/fp" --recipients "$N"
FP=(python3 benchmarks/fingerprint_multi_gpu.py run --workdir "$W/fp")
step "fp_4x$N" "${FP[@]}" --gpus 4 --limit "$N" --tag "4x$N"
step "fp_1x$N" "${FP[@]}" --gpus 1 --limit "$N" --tag "1x$N"
step compare python3 benchmarks/fingerprint_multi_gpu.py compare --workdir "$W/fp" --runs "1x$N" "4x$N" \
  --out "$W/fingerprint_long.json"
if [ "${LOCAL:-0}" = 1 ]; then
  step fp_1local "${FP[@]}" --gpus 1 --local --limit 64 --tag 1localx64
fi
log "round done"
