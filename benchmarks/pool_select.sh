#!/usr/bin/env bash
# #26 on a host with 2 GPUs (2026-11-27, eighth session): choose an early-stop setting on one lego model, then
# measure the chosen one on another (fresh messages, a model trained with another seed), beside the whole suite.
#
#   bash benchmarks/pool_select.sh WORKDIR LEGO_DIR
#
# GPU 1: lego model B (60 s, seed 1), then the whole test suite.
# GPU 0: lego model A (60 s, seed 0); tuning: one pool job of 32 recipients (K = 16) per setting in TUNE, one after
#   another on model A; the choice (the Python below): the setting with the most recipients at >= 99 % bits and
#   >= 37 dB held-out, ties broken by recipients per GPU-hour; evaluation: EVAL jobs of 32 recipients with the chosen
#   setting on model B (never used for the choice), one after another.
# With SCAN=1, once both GPUs are done: benchmarks/scan_round.sh (#27; it names 4 GPUs).
# Progress in WORKDIR/progress.log ("round done" at the end); set-up and polling as in benchmarks/gpu_round.sh.
set -uo pipefail
W=${1:?WORKDIR}
LEGO=${2:?LEGO_DIR}
. benchmarks/steps.sh
on_gpu() { local g=$1; shift; CUDA_VISIBLE_DEVICES=$g "$@"; }
FP="python3 benchmarks/fingerprint_multi_gpu.py"
TUNE=("quality,boost=3" "quality,confirm=0.998,accuracy_window=32,boost=3")

photos() { python3 -c "import json, sys; print(json.load(open(sys.argv[1]))['photos'])" "$1/prepare.json"; }
job() {  # job GPU MODEL_DIR SETTING TAG
  local d=$2
  step "$4" on_gpu "$1" python3 benchmarks/fingerprint_throughput.py --device cuda --out "$W" --scene lego \
    --model "$d/model" --data "$(photos "$d")" --budget-s 900 --setting "k=16 n=32 stop=$3" --tag "$4"
}

(step prepare_b on_gpu 1 $FP prepare --data "$LEGO" --workdir "$W/fpB" --train-seed 1
 step suite on_gpu 1 python3 -m pytest -q -p no:cacheprovider -rfE tests) &
second=$!
step prepare_a on_gpu 0 $FP prepare --data "$LEGO" --workdir "$W/fpA" --train-seed 0
for i in "${!TUNE[@]}"; do job 0 "$W/fpA" "${TUNE[$i]}" "tune_$i"; done
CHOSEN=$(python3 - "$W" "${TUNE[@]}" <<'EOF'
import json, sys
w, settings = sys.argv[1], sys.argv[2:]
best = None
for i, s in enumerate(settings):
    try:
        r = json.load(open(f"{w}/tune_{i}.json"))["sweep"][0]
    except (OSError, KeyError, IndexError, ValueError):
        continue
    key = (r["summary"]["meeting_99_and_37"], r["recipients_per_hour"])
    print(f"tune_{i} {s}: {key}", file=sys.stderr)
    if best is None or key > best[0]:
        best = (key, s)
print(best[1] if best else settings[0])
EOF
)
log "chosen: $CHOSEN"
while [ ! -s "$W/fpB/prepare.json" ] && kill -0 "$second" 2>/dev/null; do sleep 2; done
for i in $(seq 0 $((${EVAL:-2} - 1))); do job 0 "$W/fpB" "$CHOSEN" "eval_$i"; done
log "evaluation finished"
wait "$second"
log "suite finished"
if [ "${SCAN:-0}" = 1 ]; then bash benchmarks/scan_round.sh "$W"; else log "round done"; fi
