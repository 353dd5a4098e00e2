// Thread helpers of the CPU backend (on top of ATen's intra-op thread pool).
#pragma once

#include <ATen/Parallel.h>

#include <atomic>
#include <cstdint>

// Per-tile kernels are compiled twice, for x86-64-v3 (AVX2 + FMA) and for the build's baseline,
// and the loader picks the one the CPU supports (GCC/Clang function multiversioning): the pixel
// loops run 8 float lanes wide on any AVX2 machine without building with -march=native. Both
// clones are deterministic; they may differ from each other in the last bits (FMA contraction).
// GCC 12+ (ISA-level dispatch; older GCCs and Clang build the baseline only).
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 12 && \
    !defined(GSW_NO_CPU_CLONES)
#define GSW_CPU_KERNEL __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define GSW_CPU_KERNEL
#endif
// A kernel that inlines every call in its body (recursively, where possible): for kernels built
// from core/ functions, which are plain `inline` and would otherwise stay out of line, compiled
// for the baseline only.
#if defined(__GNUC__) || defined(__clang__)
#define GSW_CPU_FLATTEN __attribute__((flatten))
#else
#define GSW_CPU_FLATTEN
#endif
// Helpers of a GSW_CPU_KERNEL: always inlined, so they are compiled for the kernel's clone.
#if defined(__GNUC__) || defined(__clang__)
#define GSW_CPU_INLINE inline __attribute__((always_inline))
#else
#define GSW_CPU_INLINE inline
#endif

namespace gsw::cpu {

// Static chunks over [0, n): for uniform per-item work (per-Gaussian ops). parallel_ranges hands
// each chunk [begin, end) to fn (e.g. a GSW_CPU_KERNEL over a range), parallel_items each item.
template <typename F>
void parallel_ranges(int64_t n, F&& fn) {
  constexpr int64_t kGrain = 2048;
  at::parallel_for(0, n, kGrain, [&](int64_t begin, int64_t end) { fn(begin, end); });
}
template <typename F>
void parallel_items(int64_t n, F&& fn) {
  parallel_ranges(n, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) fn(i);
  });
}

// Dynamic scheduling over [0, n): for skewed per-item work (tiles). Each item is processed by
// exactly one thread, so results do not depend on the schedule.
template <typename F>
void parallel_dynamic(int64_t n, F&& fn) {
  if (n <= 0) return;
  std::atomic<int64_t> next{0};
  const int64_t workers = std::min<int64_t>(at::get_num_threads(), n);
  at::parallel_for(0, workers, 1, [&](int64_t begin, int64_t end) {
    for (int64_t w = begin; w < end; ++w) {
      for (int64_t i = next.fetch_add(1); i < n; i = next.fetch_add(1)) fn(i);
    }
  });
}

}  // namespace gsw::cpu
