#!/usr/bin/env bash
# The ninth session's #27 round on one host with 4 GPUs, the host to itself throughout:
#
#   bash benchmarks/multi_gpu_r9.sh WORKDIR LEGO_DIR
#
# 1. lego trained for 60 s (fingerprint_multi_gpu.py prepare);
# 2. the serial part of a Ray job broken down (ray_start.py: imports, ray.init, 4 GPU actors, shutdown, exit), with
#    Ray's default worker prestart and without it;
# 3. `gsw scan`, 10,000 files rendered from that lego at 800x800, 64 marks: 1 GPU in one process (with the decoder,
#    and host-only), four such processes side by side on a quarter of the files each (GPU i: files i, i+4, ...;
#    no Ray: whether the host limits four pipelines), then Ray Data on 1, 2 and 4 GPUs with each call's timeline,
#    and on 4 GPUs with calls of 4 x 64 sources instead of 16 x 64;
# 4. `gsw fingerprint`, 64 recipients: on 4 GPUs (a Ray cluster started by the job, then one already running),
#    2 and 1 GPU; the copies compared with the 1-GPU run's and scored on the held-out views.
# Progress in WORKDIR/progress.log ("round done" at the end); set-up and polling as in benchmarks/gpu_round.sh.
set -uo pipefail
W=${1:?WORKDIR}
LEGO=${2:?LEGO_DIR}
. benchmarks/steps.sh
step prepare python3 benchmarks/fingerprint_multi_gpu.py prepare --data "$LEGO" --workdir "$W/fp"
step ray_start python3 benchmarks/ray_start.py --workers 4 --device cuda --repeats 2 --env "" \
  --env RAY_prestart_worker_first_driver=0 --out "$W/ray_start_h200x4.json"
SC=(python3 benchmarks/scan_throughput.py --images 10000 --model "$W/fp/model" --marks 64 --device cuda --readers 8
    --workdir "$W/scan10k")
step scan_1 "${SC[@]}" --gpus 1 --modes batched,host-only,ray --out "$W/scan_1gpu.json"
log "start scan_shards"
for i in 0 1 2 3; do
  CUDA_VISIBLE_DEVICES=$i "${SC[@]}" --modes batched --shard "$i/4" --out "$W/scan_shard$i.json" \
    > "$W/scan_shard$i.log" 2>&1 &
done
wait
log "done scan_shards"
step scan_2 "${SC[@]}" --gpus 2 --modes ray --out "$W/scan_2gpu.json"
step scan_4 "${SC[@]}" --gpus 4 --modes ray --out "$W/scan_4gpu.json"
step scan_4_small "${SC[@]}" --gpus 4 --modes ray --sources-per-call 4 --out "$W/scan_4gpu_calls4.json"
FP=(python3 benchmarks/fingerprint_multi_gpu.py run --workdir "$W/fp")
step fingerprint_4 "${FP[@]}" --gpus 4
step fingerprint_4cluster "${FP[@]}" --gpus 4 --cluster
step fingerprint_2 "${FP[@]}" --gpus 2
step fingerprint_1 "${FP[@]}" --gpus 1
step compare python3 benchmarks/fingerprint_multi_gpu.py compare --runs 1 2 4 4cluster --workdir "$W/fp" \
  --out "$W/fingerprint_multi_gpu_r9.json"
log "round done"
