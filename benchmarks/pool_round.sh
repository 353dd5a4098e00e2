#!/usr/bin/env bash
# One round of #26 pool measurements on a single-GPU machine (2026-11-27, after the LPIPS references and the
# channels-last loss):
#
#   bash benchmarks/pool_round.sh WORKDIR LEGO_DIR [STEP...]     (default: the first round's steps 1-4)
#
#   1. pool_loss_ab.py: the loss pass (K = 16, 800x800) joint / split / cached / cached+nhwc / +bf16, one process;
#   2. fingerprint_multi_gpu.py prepare: lego trained ~60 s, saved with its photos;
#   3. fingerprint_throughput.py on that model: K = 16 without and with the cap extension, K = 32 with it,
#      then a 30-step profile (K = 16);
#   4. the built-in scene (256 px, 24 views, 8 held-out): 64-epoch step cap with the extension, the paper recipe
#      and freeze=f_rest;
#   window (second round, after the folded BatchNorms): lego with the extension, K = 16, without and with
#      accuracy_window=32 (32 recipients), and K = 32 with it;
#   window998 (third round): K = 16, 32 recipients, confirm 0.998 with accuracy_window=32;
#   host (next round, after the eager render dispatch, the cached background and one wavelet transform per step):
#      the loss A/B, a 30-step profile with the device's busy share and a Chrome trace, then the quality preset on
#      32 recipients (K = 16) and the throughput preset on 16.
# Set-up, progress and polling as in benchmarks/gpu_round.sh (its header).
set -uo pipefail
W=${1:?WORKDIR}
LEGO=${2:?LEGO_DIR}
. benchmarks/steps.sh
ES=throughput  # gsw.fingerprint.stopping.PRESETS: min_steps=96,window=16,margin=1,psnr_target=37.4,adapt=1.25,confirm=0.99
EX=quality     # the same with confirm=0.995,extend=0.5
TP="python3 benchmarks/fingerprint_throughput.py --device cuda --out $W"

STEPS=("${@:3}")
[ ${#STEPS[@]} -eq 0 ] && STEPS=(loss_ab prepare lego profile builtin)
PHOTOS=""
M=()
lego_model() {
  PHOTOS=$(python3 -c "import json, sys; print(json.load(open(sys.argv[1]))['photos'])" "$W/fp/prepare.json")
  M=(--scene lego --model "$W/fp/model" --data "$PHOTOS" --budget-s 900)
}
for s in "${STEPS[@]}"; do
  case $s in
    loss_ab) step loss_ab python3 benchmarks/pool_loss_ab.py --device cuda --k 16 --size 800 --out "$W/pool_loss_ab.json" ;;
    prepare) step prepare python3 benchmarks/fingerprint_multi_gpu.py prepare --data "$LEGO" --workdir "$W/fp" ;;
    lego) lego_model; step tp_lego $TP "${M[@]}" --setting "k=16 n=16 stop=$ES" --setting "k=16 n=16 stop=$EX" \
      --setting "k=32 n=32 stop=$EX" --tag lego_pool ;;
    profile) lego_model; step profile $TP "${M[@]}" --setting "k=16 n=16 stop=$ES" --profile 30 --tag lego_profile ;;
    builtin) step tp_builtin $TP --scene builtin --size 256 --budget-s 900 --setting "k=16 n=16 epochs=64 stop=$EX" \
      --setting "k=16 n=16 epochs=64 freeze=f_rest stop=$EX" --tag builtin_pool ;;
    window) lego_model; step tp_window $TP "${M[@]}" --setting "k=16 n=16 stop=$EX" \
      --setting "k=16 n=32 stop=$EX,accuracy_window=32" --setting "k=32 n=32 stop=$EX,accuracy_window=32" \
      --tag lego_window ;;
    window998) lego_model; step tp_window998 $TP "${M[@]}" \
      --setting "k=16 n=32 stop=$EX,confirm=0.998,accuracy_window=32" --tag lego_window998 ;;
    host) lego_model
      step loss_ab python3 benchmarks/pool_loss_ab.py --device cuda --k 16 --size 800 --out "$W/pool_loss_ab.json"
      step profile $TP "${M[@]}" --setting "k=16 n=16 stop=quality" --profile 30 --trace --tag lego_profile
      step tp_host $TP "${M[@]}" --setting "k=16 n=32 stop=quality" --setting "k=16 n=16 stop=throughput" \
        --tag lego_host ;;
    *) log "unknown step $s" ;;
  esac
done
log "all done"
