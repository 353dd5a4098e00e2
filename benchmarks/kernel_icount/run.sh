#!/bin/bash
# Instruction counts of the CPU blend kernels (callgrind, one serial call on fixed inputs) and their outputs,
# for A/B of kernel changes: counts are repeatable where wall times on a shared machine are not.
#   benchmarks/kernel_icount/run.sh SRCROOT DATADIR MODE
# builds harness.cpp against SRCROOT/csrc (another checkout, e.g. `git worktree add /tmp/old <commit>`) with the
# extension's flags, prints the kernel's instruction count and writes DATADIR.MODE.<commit>.out (compare two builds'
# outputs with cmp). DATADIR: from dump_inputs.py; MODE: fwd | bwd | bwdfull (harness.cpp).
set -e
here=$(cd "$(dirname "$0")" && pwd)
src=$(cd "$1" && pwd); data=$2; mode=$3
if git -C "$src" rev-parse --git-dir >/dev/null 2>&1; then
  tag=$(git -C "$src" rev-parse --short HEAD)$(git -C "$src" diff --quiet HEAD -- csrc || echo +)  # +: uncommitted csrc changes
else
  tag=$(basename "$src")
fi
bin=$(mktemp /tmp/gsw_harness.XXXXXX)
g++ -O3 -DNDEBUG -std=gnu++17 -fno-trapping-math -fno-math-errno -Wno-psabi -I"$here" -I"$src/csrc" \
  "$here/harness.cpp" "$src/csrc/cpu/rasterize_cpu.cpp" -o "$bin"
valgrind --tool=callgrind --callgrind-out-file="$bin.cg" "$bin" "$data" "$mode" 1 "$data.$mode.$tag.out" 2>/dev/null
kernel=$([ "$mode" = fwd ] && echo forward || echo backward)
echo "$tag $data $mode: $(callgrind_annotate --inclusive=yes "$bin.cg" 2>/dev/null |
  grep -m1 "rasterize_$kernel<float>" | awk '{print $1}') instructions (gsw::cpu::rasterize_$kernel<float>, 1 thread)"
rm -f "$bin" "$bin.cg"
