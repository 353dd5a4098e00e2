#!/usr/bin/env bash
# Rasterizer rounds on one GPU (issue #24; eleventh and twelfth sessions):
#   bash benchmarks/gpu_kernels.sh setup     # wheels from .whl into /tmp/site2, `jit`, CUDA build of gsw
#   bash benchmarks/gpu_kernels.sh jit       # gsplat's CUDA code compiled in the background (/tmp/gsplat_jit.log)
#   bash benchmarks/gpu_kernels.sh waitjit   # wait for that compilation
#   bash benchmarks/gpu_kernels.sh suite     # the whole test suite with this CUDA build
#   bash benchmarks/gpu_kernels.sh bench OUT TAG  # bench_cuda.py: atomic vs deterministic blend backward (auto, px4), the
#                                              # contribution's layouts (auto, px4, px2), gsplat side by side
#   bash benchmarks/gpu_kernels.sh kernels OUT [TAG]  # kernel_times.py: each CUDA kernel's share of a forward / forward+backward
#   bash benchmarks/gpu_kernels.sh memory OUT [TAG]   # memory_peak.py: what is live at the peak of a forward+backward
#                                              # (KEEP=1: the image kept through the backward, as bench_cuda.py)
#   bash benchmarks/gpu_kernels.sh budget OUT [TAG]   # records_budget.py: time and peak per blend-records budget
#   bash benchmarks/gpu_kernels.sh ncu OUT [CASE]  # Nsight Compute: the blend forward and contribution kernels of CASE
#   bash benchmarks/gpu_kernels.sh lego_train OUT TAG  # lego trained here for 60 s (build/gpu/lego carried)
#   bash benchmarks/gpu_kernels.sh lego OUT TAG  # that model (trained first if none), gsplat side by side
#   bash benchmarks/gpu_kernels.sh cut OUT TAG  # the blend backward's layouts (auto, px2, px4) on that model at 400 / 800 /
#                                              # 1600 px and two synthetic cases, with auto's cut length free and fixed
#                                              # at 128 / 192 / 256 splats (GSW_CUDA_CHUNK), and the tile counts behind
#                                              # auto's choice (tile_load.py; BENCHMARKS.md 2s)
#   bash benchmarks/gpu_kernels.sh lego_kernels OUT TAG  # kernel_times.py on that model
#   bash benchmarks/gpu_kernels.sh base DIR    # an A/B baseline: this tree with DIR's files over it (e.g. the last
#                                              # commit's csrc/ and gsw/: `git archive HEAD csrc gsw | tar -x -C DIR`),
#                                              # built into /tmp/gsw_base (not editable)
#   BASE=1 bash benchmarks/gpu_kernels.sh kernels|bench ...  # run on that baseline build (python -S: the editable
#                                              # build's import hook does not load)
# Carry .whl (kornia, kornia_rs, scikit_build_core, pybind11, pathspec, gsplat wheels) in the setup call and
# build/gpu/ply (../shared/data/ply/sh3_fixture) in the bench call (64-MiB transfer limit).
set -uo pipefail
export PYTHONPATH=/tmp/site2 PATH=/tmp/site2/bin:$PATH TORCH_CUDA_ARCH_LIST=9.0
PY=(python3)
if [ -n "${BASE:-}" ]; then
  SP=$(python3 -c "import os, torch; print(os.path.dirname(os.path.dirname(torch.__file__)))")
  export PYTHONPATH=/tmp/gsw_base:/tmp/site2:$SP
  PY=(python3 -S)
fi
case "$1" in
  setup)
    python3 -m pip install -q --no-deps --target /tmp/site2 .whl/*.whl
    bash "$0" jit  # gsplat compiles beside gsw's build
    GSW_WITH_CUDA=ON python3 -m pip install -q --no-build-isolation --no-deps -e . || exit 1
    python3 -c "import gsw; print(gsw.build_info())"
    ;;
  jit)  # gsplat compiles its CUDA code at first use: do it now, in the background
    setsid nohup python3 -c "
import torch, gsplat
m = torch.zeros(1, 3, device='cuda'); m[:, 2] = 3
q = torch.tensor([[1., 0, 0, 0]], device='cuda'); s = torch.full((1, 3), 0.1, device='cuda')
o = torch.ones(1, device='cuda'); c = torch.ones(1, 3, device='cuda')
K = torch.tensor([[[50., 0, 32], [0, 50., 32], [0, 0, 1]]], device='cuda')
gsplat.rasterization(m, q, s, o, c, torch.eye(4, device='cuda')[None], K, 64, 64)
print('gsplat ready', gsplat.__version__)" > /tmp/gsplat_jit.log 2>&1 < /dev/null &
    ;;
  waitjit)  # until gsplat's background compilation is done (at most 5 minutes)
    for _ in $(seq 1 100); do grep -q "gsplat ready" /tmp/gsplat_jit.log 2>/dev/null && break; sleep 3; done
    tail -1 /tmp/gsplat_jit.log
    ;;
  base)
    rm -rf /tmp/base && mkdir /tmp/base && cp -r benchmarks csrc gsw CMakeLists.txt pyproject.toml README.md /tmp/base/ &&
      cp -r "${2:?DIR}"/. /tmp/base/ || exit 1
    (cd /tmp/base && GSW_WITH_CUDA=ON python3 -m pip install -q --no-build-isolation --no-deps --target /tmp/gsw_base .) || exit 1
    BASE=1 bash "$0" info
    ;;
  info)
    (cd /tmp && "${PY[@]}" -c "import gsw; print(gsw.__file__, gsw.build_info())")
    ;;
  suite)
    python3 -m pytest -q -p no:cacheprovider -rfE tests 2>&1 | tail -40
    ;;
  bench)
    OUT=${2:?OUT} TAG=${3:?TAG}
    cat /tmp/gsplat_jit.log
    "${PY[@]}" benchmarks/bench_cuda.py --reps 10 --warmup 3 --backward atomic auto px4 --contribution auto px4 px2 \
      --ply build/gpu/ply/sh3_fixture/point_cloud.ply \
      --cases frustum:100000:800x800 heavy:100000:800x800 frustum:1000000:1920x1080 heavy:1000000:1920x1080 \
              frustum:3000000:1920x1080 heavy:3000000:1920x1080 frustum:1000000:3840x2160 heavy:1000000:3840x2160 \
              ply:9080:1920x1080 ply:9080:3840x2160 \
      --commit "$(git rev-parse --short HEAD 2>/dev/null)+$TAG" --out "$OUT/cuda_$TAG.json" --md "$OUT/cuda_$TAG.md" 2>&1 | tail -60
    ;;
  lego_train)  # a lego model trained on this machine for 60 s (may run beside `suite`)
    python3 benchmarks/train_lego.py --device cuda --preset inria --time-budget-s 60 --data build/gpu/lego \
      --no-progress --tag "train_lego_cuda_$3" > /tmp/train_lego.log 2>&1 || { tail -20 /tmp/train_lego.log; exit 1; }
    cp "benchmarks/results/train_lego_cuda_$3.json" "$2/" 2>/dev/null
    tail -3 /tmp/train_lego.log
    ;;
  lego)  # that model (trained first if this machine has none), against gsplat at 1x and 2x render size
    P=$(find build/train_lego -name point_cloud.ply 2>/dev/null | sort | tail -1)
    if [ -z "$P" ]; then
      bash "$0" lego_train "$2" "$3" || exit 1
      P=$(find build/train_lego -name point_cloud.ply | sort | tail -1)
    fi
    "${PY[@]}" benchmarks/bench_cuda.py --reps 10 --warmup 3 --backward auto px4 px2 --contribution auto px4 px2 --ply "$P" \
      --cases ply:0:800x800 ply:0:1600x1600 \
      --commit "$(git rev-parse --short HEAD 2>/dev/null)+$3" --out "$2/cuda_lego_$3.json" --md "$2/cuda_lego_$3.md" 2>&1 | tail -20
    ;;
  cut)  # the blend backward's layouts per cut length, and the tile counts (no gsplat)
    P=$(find build/train_lego -name point_cloud.ply 2>/dev/null | sort | tail -1)
    if [ -z "$P" ]; then
      bash "$0" lego_train "$2" "$3" || exit 1
      P=$(find build/train_lego -name point_cloud.ply | sort | tail -1)
    fi
    CASES=(ply:0:400x400 ply:0:800x800 ply:0:1600x1600 frustum:100000:800x800 heavy:1000000:1920x1080)
    "${PY[@]}" benchmarks/tile_load.py --ply "$P" --cases "${CASES[@]}" 2>&1 | grep -v Warning
    for CHUNK in "" 128 192 256; do
      GSW_CUDA_CHUNK=$CHUNK "${PY[@]}" benchmarks/bench_cuda.py --reps 10 --warmup 3 --no-gsplat --backward auto px2 px4 \
        --ply "$P" --cases "${CASES[@]}" \
        --commit "$(git rev-parse --short HEAD 2>/dev/null)+$3" --out "$2/cuda_cut_${3}_chunk${CHUNK:-auto}.json" \
        --md "$2/cuda_cut_${3}_chunk${CHUNK:-auto}.md" 2>&1 | grep -A9 "blend backward variants" | tail -7
    done
    ;;
  lego_kernels)  # kernel_times.py on that model (trained first if this machine has none) at 1x and 2x render size
    P=$(find build/train_lego -name point_cloud.ply 2>/dev/null | sort | tail -1)
    if [ -z "$P" ]; then
      bash "$0" lego_train "$2" "$3" || exit 1
      P=$(find build/train_lego -name point_cloud.ply | sort | tail -1)
    fi
    "${PY[@]}" benchmarks/kernel_times.py --ply "$P" --json "$2/kernel_times_lego_$3.json" \
      --cases ply:0:800x800 ply:0:1600x1600 2>&1 | grep -v Warning | cut -c1-130
    ;;
  ncu)  # Nsight Compute on the blend forward and the contribution kernel of one case (the second forward, the first
        # contribution after a warm-up forward), clocks left alone
    CASE=${3:-frustum:1000000:3840x2160}
    ncu --clock-control none -k regex:'(^|::)(forward|contribution)_kernel' --launch-skip 1 --launch-count 2 \
      --section SpeedOfLight --section Occupancy --section LaunchStats --section WarpStateStats \
      --section SchedulerStats --section MemoryWorkloadAnalysis --section ComputeWorkloadAnalysis \
      "${PY[@]}" -c "
import sys, torch, gsw
sys.path.insert(0, 'benchmarks')
from bench_cuda import make_scene
f, n, s = '$CASE'.split(':'); w, h = map(int, s.split('x'))
g, cam = make_scene(f, int(n), w, h, 'build/gpu/ply/sh3_fixture/point_cloud.ply')
wt = torch.rand(3, h, w, device='cuda')
with torch.no_grad():
    gsw.rasterize(g, cam, validate=False); gsw.rasterize(g, cam, validate=False)
gsw.contribution(g, cam, wt); gsw.contribution(g, cam, wt)
torch.cuda.synchronize()
" > "$2/ncu_${CASE//:/_}.txt" 2>&1; grep -E "Duration|Throughput|Warp Cycles Per Issued|Achieved Occupancy|Registers Per|Stall|Issued Warp|No Eligible|One or More" "$2/ncu_${CASE//:/_}.txt" | head -60
    ;;
  memory)  # what is live at the peak of one forward+backward, gsw and gsplat
    "${PY[@]}" benchmarks/memory_peak.py ${KEEP:+--keep-image} --ply build/gpu/ply/sh3_fixture/point_cloud.ply \
      --out "$2/memory_peak_${3:-new}.json" --commit "$(git rev-parse --short HEAD 2>/dev/null)+${3:-new}" \
      --cases frustum:100000:800x800 frustum:1000000:1920x1080 frustum:3000000:1920x1080 frustum:1000000:3840x2160 \
              ply:9080:1920x1080 ply:9080:3840x2160 heavy:1000000:1920x1080 2>&1 | grep -v Warning | cut -c1-160
    ;;
  budget)  # forward+backward time and peak memory per blend-records budget, gsplat packed=False beside
    "${PY[@]}" benchmarks/records_budget.py --ply build/gpu/ply/sh3_fixture/point_cloud.ply --out "$2/records_budget_${3:-new}.json" \
      --commit "$(git rev-parse --short HEAD 2>/dev/null)+${3:-new}" --budgets default 0 64 32 16 8 2>&1 | grep -v Warning
    ;;
  kernels)
    "${PY[@]}" benchmarks/kernel_times.py --ply build/gpu/ply/sh3_fixture/point_cloud.ply --json "$2/kernel_times_${3:-new}.json" \
      --cases frustum:100000:800x800 frustum:3000000:1920x1080 heavy:1000000:1920x1080 frustum:1000000:3840x2160 \
              heavy:1000000:3840x2160 ply:9080:3840x2160 2>&1 | grep -v Warning | cut -c1-130
    ;;
esac
