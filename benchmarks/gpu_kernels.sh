#!/usr/bin/env bash
# Rasterizer rounds on one GPU (issue #24; eleventh and twelfth sessions):
#   bash benchmarks/gpu_kernels.sh setup     # wheels from .whl into /tmp/site2, CUDA build of gsw
#   bash benchmarks/gpu_kernels.sh jit       # gsplat's CUDA code compiled in the background (/tmp/gsplat_jit.log)
#   bash benchmarks/gpu_kernels.sh suite     # the whole test suite with this CUDA build
#   bash benchmarks/gpu_kernels.sh bench OUT TAG  # bench_cuda.py: atomic vs deterministic blend backward, gsplat side by side
#   bash benchmarks/gpu_kernels.sh kernels OUT [TAG]  # kernel_times.py: each CUDA kernel's share of a forward / forward+backward
#   bash benchmarks/gpu_kernels.sh base DIR    # an A/B baseline: this tree with DIR's files over csrc/ (e.g. the last
#                                              # commit's), built into /tmp/gsw_base (not editable)
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
  base)
    rm -rf /tmp/base && mkdir /tmp/base && cp -r benchmarks csrc gsw CMakeLists.txt pyproject.toml README.md /tmp/base/ &&
      cp -r "${2:?DIR}"/. /tmp/base/csrc/ || exit 1
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
    "${PY[@]}" benchmarks/bench_cuda.py --reps 10 --warmup 3 --backward atomic px4 --ply build/gpu/ply/sh3_fixture/point_cloud.ply \
      --cases frustum:100000:800x800 heavy:100000:800x800 frustum:1000000:1920x1080 heavy:1000000:1920x1080 \
              frustum:3000000:1920x1080 heavy:3000000:1920x1080 frustum:1000000:3840x2160 heavy:1000000:3840x2160 \
              ply:9080:1920x1080 ply:9080:3840x2160 \
      --commit "$(git rev-parse --short HEAD 2>/dev/null)+$TAG" --out "$OUT/cuda_$TAG.json" --md "$OUT/cuda_$TAG.md" 2>&1 | tail -60
    ;;
  kernels)
    "${PY[@]}" benchmarks/kernel_times.py --ply build/gpu/ply/sh3_fixture/point_cloud.ply --json "$2/kernel_times_${3:-new}.json" \
      --cases frustum:100000:800x800 frustum:3000000:1920x1080 heavy:1000000:1920x1080 frustum:1000000:3840x2160 \
              heavy:1000000:3840x2160 ply:9080:3840x2160 2>&1 | grep -v Warning | cut -c1-130
    ;;
esac
