#!/usr/bin/env bash
# #26 on a host with 2 GPUs (2026-11-28, seventeenth session): `EarlyStop.redraw` measured on fresh models and
# messages, and the whole test suite with this CUDA build.
#
#   bash benchmarks/redraw_round.sh WORKDIR LEGO_DIR
#
# GPU 1: the whole test suite (started by the set-up call: `benchmarks/redraw_round.sh WORKDIR - suite`, which
#        returns once the suite has collected; its exit status lands in WORKDIR/suite.rc), then, once it is done,
#        lego trained 60 s with train seed 5 and one pool job on it.
# GPU 0: lego trained 60 s with train seed 4 and one pool job on it, then one job on the built-in scene (256x256,
#        24 embedding / 8 held-out views, 64-epoch cap).
# Each job: K = 16, 64 fresh secret 32-bit messages, `--early-stop careful,redraw=2` (the redraw rule's threshold,
# 0.995 on the embedding views, was read off the earlier rounds' jobs; these models and messages are new).
# Set-up, progress and polling as in benchmarks/gpu_round.sh (its header). The set-up call carries .whl (with
# gsplat, for the suite's comparisons), the next one build/gpu/lego (64-MiB transfer limit).
set -uo pipefail
W=${1:?WORKDIR}
LEGO=${2:?LEGO_DIR}
. benchmarks/steps.sh
STOP="careful,redraw=2"
on_gpu() { local g=$1; shift; CUDA_VISIBLE_DEVICES=$g "$@"; }
lego_job() {  # GPU SEED
  local g=$1 seed=$2 fp="$W/fp$2"
  step "prepare$seed" on_gpu "$g" python3 benchmarks/fingerprint_multi_gpu.py prepare --data "$LEGO" --workdir "$fp" \
    --train-seed "$seed"
  local photos
  photos=$(python3 -c "import json, sys; print(json.load(open(sys.argv[1]))['photos'])" "$fp/prepare.json")
  step "job$seed" on_gpu "$g" python3 benchmarks/fingerprint_throughput.py --device cuda --out "$W" --scene lego \
    --model "$fp/model" --data "$photos" --budget-s 900 --setting "k=16 n=64 stop=$STOP" \
    --tag "fingerprint_lego_h200_redraw_r17_seed$seed"
}
if [ "${3:-}" = suite ]; then
  CUDA_VISIBLE_DEVICES=1 setsid nohup bash -c 'python3 -m pytest -q -p no:cacheprovider -rfE tests > "$0/suite.log" 2>&1
    echo $? > "$0/suite.rc"' "$W" > /dev/null 2>&1 &
  until grep -q '%]' "$W/suite.log" 2>/dev/null || [ -f "$W/suite.rc" ]; do sleep 2; done  # collected
  log "suite collected"
  exit 0
fi
( until [ -f "$W/suite.rc" ]; do sleep 5; done; log "suite exit $(cat "$W/suite.rc")"; lego_job 1 5 ) &
( lego_job 0 4
  step builtin on_gpu 0 python3 benchmarks/fingerprint_throughput.py --device cuda --out "$W" --scene builtin \
    --size 256 --views 24 --held-out 8 --budget-s 900 --setting "k=16 n=64 epochs=64 stop=$STOP" \
    --tag "fingerprint_builtin_h200_redraw_r17" ) &
wait
log "round done"
