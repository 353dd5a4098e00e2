#!/usr/bin/env bash
# Eleventh GPU round (issue #24: blend backward records for the visited splats only), on one GPU:
#   bash benchmarks/gpu_r11.sh setup     # wheels from .whl into /tmp/site2, CUDA build of gsw
#   bash benchmarks/gpu_r11.sh jit       # gsplat's CUDA code compiled in the background (/tmp/gsplat_jit.log)
#   bash benchmarks/gpu_r11.sh suite     # the whole test suite with this CUDA build
#   bash benchmarks/gpu_r11.sh bench OUT TAG  # bench_cuda.py: atomic vs deterministic blend backward, gsplat side by side
#   bash benchmarks/gpu_r11.sh kernels OUT  # kernel_times.py: each CUDA kernel's share of a forward / forward+backward
# Carry .whl (kornia, kornia_rs, scikit_build_core, pybind11, pathspec, gsplat wheels) in the setup call and
# build/gpu/ply (../shared/data/ply/sh3_fixture) in the bench call (64-MiB transfer limit).
set -uo pipefail
export PYTHONPATH=/tmp/site2 PATH=/tmp/site2/bin:$PATH TORCH_CUDA_ARCH_LIST=9.0
case "$1" in
  setup)
    python3 -m pip install -q --no-deps --target /tmp/site2 .whl/*.whl
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
  suite)
    python3 -m pytest -q -p no:cacheprovider -rfE tests 2>&1 | tail -40
    ;;
  bench)
    OUT=${2:?OUT} TAG=${3:?TAG}
    cat /tmp/gsplat_jit.log
    python3 benchmarks/bench_cuda.py --reps 10 --warmup 3 --backward atomic px4 --ply build/gpu/ply/sh3_fixture/point_cloud.ply \
      --cases frustum:100000:800x800 heavy:100000:800x800 frustum:1000000:1920x1080 heavy:1000000:1920x1080 \
              frustum:3000000:1920x1080 heavy:3000000:1920x1080 frustum:1000000:3840x2160 heavy:1000000:3840x2160 \
              ply:9080:1920x1080 ply:9080:3840x2160 \
      --commit "$(git rev-parse --short HEAD 2>/dev/null)+$TAG" --out "$OUT/cuda_$TAG.json" --md "$OUT/cuda_$TAG.md" 2>&1 | tail -60
    ;;
  kernels)
    python3 benchmarks/kernel_times.py --ply build/gpu/ply/sh3_fixture/point_cloud.ply --json "$2/kernel_times.json" \
      --cases frustum:100000:800x800 frustum:3000000:1920x1080 heavy:1000000:1920x1080 frustum:1000000:3840x2160 \
              heavy:1000000:3840x2160 ply:9080:3840x2160 2>&1 | grep -v Warning | cut -c1-130
    ;;
esac
