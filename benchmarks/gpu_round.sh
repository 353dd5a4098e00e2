#!/usr/bin/env bash
# One round of GPU work on a host with 4 GPUs (2026-11-27, issues #26 #27; the whole suite for every C++/CUDA change):
#
#   bash benchmarks/gpu_round.sh WORKDIR LEGO_DIR      (SUITE_PID=PID: the suite already runs; wait for it)
#
#   GPU 3: the whole test suite with this CUDA build (unless SUITE_PID: started earlier, e.g. right after the build);
#   GPU 0: fingerprint_multi_gpu.py prepare (lego trained 60 s), then the pool's profile (torch.profiler);
#   GPUs 1-2, while the suite runs: `gsw.fingerprint` in one process on the saved lego model with the photos,
#          held-out quality (#26): GPU 1 K = 16 with the PSNR control at 37.4 and 37.6 dB, GPU 2 K = 32 at 37.6 dB;
#   then, the host otherwise idle: `gsw scan` over 10,000 files on 1, 2 and 4 GPUs (Ray Data), then
#          `gsw fingerprint` through Ray on 4 and 1 GPUs, compare.
#
# Progress in WORKDIR/progress.log, each step's output in WORKDIR/<step>.log, results WORKDIR/*.json / *.txt.
#
# Set-up on an offline GPU machine (torch preinstalled; .whl = kornia, kornia_rs, scikit_build_core, pybind11,
# pathspec wheels, .whl-ray = benchmarks/ray_bundle.sh's bundle, build/gpu/lego = the WebP photos of power_lego.py
# --pack-webp; the tracked tree is ~45 MiB of the 64-MiB transfer limit, so each is carried in its own call):
#   sh .whl-ray/INSTALL.sh && python3 -m pip install -q --no-deps --target /tmp/site2 .whl/*.whl
#   export PYTHONPATH=/tmp/site:/tmp/site2 PATH=/tmp/site2/bin:/tmp/site/bin:$PATH
#   TORCH_CUDA_ARCH_LIST=9.0 GSW_WITH_CUDA=ON python3 -m pip install -q --no-build-isolation --no-deps -e .
# then start this script with setsid nohup ... & and poll WORKDIR/progress.log without gaps (an idle machine is
# taken back after 30 s). Every device call copies the working tree afresh and the editable install imports gsw
# from it: a suite started in one call and still collecting when the next call starts fails with missing files
# (2026-11-27: 37 collection errors). Start the suite in the last call that carries files, then poll with long
# calls (few re-copies).
set -uo pipefail
W=${1:?WORKDIR}
LEGO=${2:?LEGO_DIR}
. benchmarks/steps.sh
on_gpu() { local g=$1; shift; CUDA_VISIBLE_DEVICES=$g "$@"; }
FP="python3 benchmarks/fingerprint_multi_gpu.py"
TP="python3 benchmarks/fingerprint_throughput.py --scene lego --device cuda --out $W"
ES="min_steps=96,window=16,margin=1,psnr_target=37.4,adapt=1.25,confirm=0.99"
ES376=${ES/37.4/37.6}

if [ -z "${SUITE_PID:-}" ]; then
  step suite on_gpu 3 python3 -m pytest -q -p no:cacheprovider -rfE tests &
  SUITE_PID=$!
fi
step prepare on_gpu 0 $FP prepare --data "$LEGO" --workdir "$W/fp"
PHOTOS=$(python3 -c "import json, sys; print(json.load(open(sys.argv[1]))['photos'])" "$W/fp/prepare.json")
M=(--model "$W/fp/model" --data "$PHOTOS" --budget-s 600)
step tp_k16 on_gpu 1 $TP "${M[@]}" --setting "k=16 n=16 stop=$ES" --setting "k=16 n=16 stop=$ES376" --tag tp_k16 &
p1=$!
step tp_k32 on_gpu 2 $TP "${M[@]}" --setting "k=32 n=32 stop=$ES376" --tag tp_k32 &
p2=$!
step profile on_gpu 0 $TP "${M[@]}" --setting "k=16 n=16 stop=$ES" --profile 30 --tag pool_profile
wait $p1 $p2
while kill -0 "$SUITE_PID" 2>/dev/null; do sleep 2; done
log "suite finished"
SC=(python3 benchmarks/scan_throughput.py --images 10000 --model "$W/fp/model" --marks 64 --device cuda --readers 8
    --modes ray --workdir "$W/scan10k")
for g in 1 2 4; do
  step "scan_$g" "${SC[@]}" --gpus "$g" --out "$W/scan_cuda_${g}gpu.json"
done
for g in 4 1; do
  step "fingerprint_$g" $FP run --gpus "$g" --workdir "$W/fp"
done
step compare $FP compare --runs 1 4 --workdir "$W/fp" --out "$W/fingerprint_multi_gpu.json"
log "all done"
