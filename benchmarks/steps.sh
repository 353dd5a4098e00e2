# Sourced by the GPU run scripts (multi_gpu_run.sh, gpu_round.sh, multi_gpu_r27.sh, ...) after they set W (the
# work folder):
# NVLink multicast off (the device documentation asks for it; nothing here uses NCCL), unbuffered Python, and
#   log TEXT            a timestamped line on stdout and in $W/progress.log;
#   step NAME CMD...    runs CMD with its output in $W/NAME.log, logging its start and end (a failure is logged,
#                       not fatal: the later steps still run);
#   snapshot_build      (in the repo root) copies the tree into $W/src/main, moves there and builds gsw there for the
#                       H200s (sm_90, CUDA; kornia in /tmp/site2, Ray in /tmp/site): every device call copies the
#                       working tree afresh, so a step started in one call must not run code the next call's copy
#                       replaces.
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1 PYTHONUNBUFFERED=1
mkdir -p "$W"
log() { echo "[$(date -u +%T)] $*" | tee -a "$W/progress.log"; }
step() {
  local name=$1; shift
  log "start $name"
  if "$@" >"$W/$name.log" 2>&1; then log "done $name"; else log "FAILED $name (exit $?)"; fi
}
snapshot_build() {
  local src=$W/src/main
  mkdir -p "$src"
  for f in * .ci; do [ "$f" = build ] || cp -r "$f" "$src"/; done  # the tree, not its build outputs
  [ -d ../shared ] && ln -sfn "$(cd ../shared && pwd)" "$W/src/shared"
  cd "$src" || return 1
  export PYTHONPATH=/tmp/site2:/tmp/site PATH=/tmp/site2/bin:/tmp/site/bin:$PATH TORCH_CUDA_ARCH_LIST=9.0
  step build env GSW_WITH_CUDA=ON python3 -m pip install -q --no-build-isolation --no-deps -e .
  python3 -c "import gsw; print(gsw.build_info())" >>"$W/progress.log" 2>&1
}
