#!/usr/bin/env bash
# One round of GPU work on a host with 4 GPUs, arranged so that no GPU waits (2026-11-26, issues #24 #26 #27):
#
#   bash benchmarks/gpu_round.sh WORKDIR LEGO_DIR
#
#   GPU 3: the whole test suite with this CUDA build (gsplat's JIT build beside it), then the CUDA rasterizer
#          benchmark against gsplat (bench_cuda.py: both gsplat modes; synthetic families and the lego model
#          trained below; the blend backward A/B: atomic vs the deterministic px4) beside the 1- and 2-GPU runs;
#   GPU 0: fingerprint_multi_gpu.py prepare (lego trained 60 s);
#   GPUs 0-2, while the suite runs (no Ray there): why `gsw fingerprint` copies read 32 dB held-out when the
#          in-process pool reads 37 (BENCHMARKS.md, #27): the same saved model through the API with the photos
#          (GPU 0), the API without photos (GPU 1), `gsw fingerprint --local` without `--images` on 16 recipients
#          (GPU 2);
#   then `gsw fingerprint` on 1, 2 and 4 GPUs through Ray (the 4-GPU run alone on the host), compare, and
#          `gsw scan` over 10,000 files on 1, 2 and 4 GPUs (benchmarks/multi_gpu_run.sh's steps).
#
# Progress in WORKDIR/progress.log, each step's output in WORKDIR/<step>.log, results WORKDIR/*.json / *.md.
set -uo pipefail
W=${1:?WORKDIR}
LEGO=${2:?LEGO_DIR}
. benchmarks/steps.sh
on_gpu() { local g=$1; shift; CUDA_VISIBLE_DEVICES=$g "$@"; }
FP="python3 benchmarks/fingerprint_multi_gpu.py"
ES="min_steps=96,window=16,margin=1,psnr_target=37.4,adapt=1.25,confirm=0.99"

step suite on_gpu 3 python3 -m pytest -q -p no:cacheprovider -rfE tests &
suite=$!
# gsplat's CUDA extension is JIT-compiled at first use: now, while no timed run is going
step gsplat_build on_gpu 3 python3 -c "import torch, gsplat; from gsplat.cuda._backend import _C; print(gsplat.__version__, _C)" &
gbuild=$!
step prepare on_gpu 0 $FP prepare --data "$LEGO" --workdir "$W/fp"
step diag_api_photos on_gpu 0 python3 benchmarks/fingerprint_throughput.py --scene lego --model "$W/fp/model" \
  --data "$W/fp/lego_png" --setting "k=16 n=16 stop=$ES" --device cuda --tag diag_api_photos --out "$W" &
d0=$!
step diag_api_nophotos on_gpu 1 python3 benchmarks/fingerprint_throughput.py --scene lego --model "$W/fp/model" \
  --data "$W/fp/lego_png" --setting "k=16 n=16 stop=$ES" --no-photos --device cuda --tag diag_api_nophotos \
  --out "$W" &
d1=$!
step diag_cli_local $FP run --gpus 1 --first-gpu 2 --local --no-photos --limit 16 --workdir "$W/fp" &
d2=$!
wait $suite $gbuild
LEGO_PLY="$W/fp/model/point_cloud/iteration_0/point_cloud.ply"
step bench_cuda on_gpu 3 python3 benchmarks/bench_cuda.py --reps 10 --warmup 3 --backward atomic px4 \
  --ply "$LEGO_PLY" --cases frustum:100000:800x800 heavy:100000:800x800 frustum:1000000:1920x1080 \
  heavy:1000000:1920x1080 frustum:3000000:1920x1080 heavy:3000000:1920x1080 frustum:1000000:3840x2160 \
  heavy:1000000:3840x2160 ply:0:800x800 ply:0:1600x1600 \
  --out "$W/cuda_bench.json" --md "$W/cuda_bench.md" &
bench=$!
wait $d0 $d1 $d2
step fingerprint_1 $FP run --gpus 1 --workdir "$W/fp"
step fingerprint_2 $FP run --gpus 2 --workdir "$W/fp"
wait $bench
step fingerprint_4 $FP run --gpus 4 --workdir "$W/fp"
step compare $FP compare --runs 1 2 4 1localnophotosx16 --workdir "$W/fp" --out "$W/fingerprint_multi_gpu.json"
FINGERPRINT=0 GPUS="1 2 4" bash benchmarks/multi_gpu_run.sh "$W" "$LEGO"  # the scans
