#!/usr/bin/env bash
# The #27 run on one host with several GPUs: `gsw fingerprint` (lego 800x800, 32 bits, --recipients
# recipients) and `gsw scan` (10,000 files against 64 marks) on each GPU count of $GPUS, through Ray.
#
#   GPUS="1 2" bash benchmarks/multi_gpu_run.sh WORKDIR LEGO_DIR     (FINGERPRINT=0: scans only; SCANS=0: no scans)
#
# Steps (each logged to WORKDIR/progress.log; results WORKDIR/*.json): fingerprint_multi_gpu.py prepare
# (trains lego 60 s), run on each GPU count, compare; then scan_throughput.py over a crawl of 10,000 files
# rendered from the same lego model: per-source (500 files), batched and Ray on 1 GPU, Ray on the others.
# NVLink multicast stays off (the device documentation asks for it; nothing here uses NCCL). Ray must be
# importable: on the offline GPU machines, carry the bundle of benchmarks/ray_bundle.sh and run its INSTALL.sh.
set -uo pipefail
W=${1:?WORKDIR}
LEGO=${2:?LEGO_DIR}
GPUS=${GPUS:-"1 2"}
FINGERPRINT=${FINGERPRINT:-1}  # 0: the scans only (of an earlier run's WORKDIR/fp/model)
SCANS=${SCANS:-1}  # 0: the fingerprint runs only
. benchmarks/steps.sh
if [ "$FINGERPRINT" != 0 ]; then
  step prepare python3 benchmarks/fingerprint_multi_gpu.py prepare --data "$LEGO" --workdir "$W/fp"
  for g in $GPUS; do
    step "fingerprint_$g" python3 benchmarks/fingerprint_multi_gpu.py run --gpus "$g" --workdir "$W/fp"
  done
  # shellcheck disable=SC2086
  step compare python3 benchmarks/fingerprint_multi_gpu.py compare --runs $GPUS --workdir "$W/fp" \
    --out "$W/fingerprint_multi_gpu.json"
fi
[ "$SCANS" = 0 ] && { log "all done (no scans)"; exit 0; }
for g in $GPUS; do
  modes=ray
  extra=()
  if [ "$g" = 1 ]; then modes=per-source,batched,ray; extra=(--per-source-images 500); fi
  step "scan_$g" python3 benchmarks/scan_throughput.py --images 10000 --model "$W/fp/model" --marks 64 \
    --device cuda --gpus "$g" --readers 8 --modes "$modes" "${extra[@]}" --workdir "$W/scan10k" \
    --out "$W/scan_cuda_${g}gpu.json"
done
log "all done"
