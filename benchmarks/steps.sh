# Sourced by the GPU run scripts (multi_gpu_run.sh, gpu_round.sh) after they set W (the work folder):
# NVLink multicast off (the device documentation asks for it; nothing here uses NCCL), unbuffered Python, and
#   log TEXT            a timestamped line on stdout and in $W/progress.log;
#   step NAME CMD...    runs CMD with its output in $W/NAME.log, logging its start and end (a failure is logged,
#                       not fatal: the later steps still run).
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1 PYTHONUNBUFFERED=1
mkdir -p "$W"
log() { echo "[$(date -u +%T)] $*" | tee -a "$W/progress.log"; }
step() {
  local name=$1; shift
  log "start $name"
  if "$@" >"$W/$name.log" 2>&1; then log "done $name"; else log "FAILED $name (exit $?)"; fi
}
