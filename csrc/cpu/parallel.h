// Thread helpers of the CPU backend (on top of ATen's intra-op thread pool).
#pragma once

#include <ATen/Parallel.h>

#include <atomic>
#include <cstdint>

namespace gsw::cpu {

// Static chunks over [0, n): for uniform per-item work (per-Gaussian ops).
template <typename F>
void parallel_items(int64_t n, F&& fn) {
  constexpr int64_t kGrain = 2048;
  at::parallel_for(0, n, kGrain, [&](int64_t begin, int64_t end) {
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
