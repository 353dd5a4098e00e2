// Serial stand-in for ATen's parallel_for and thread count: harness.cpp runs the kernels on one thread.
#pragma once
#include <cstdint>
namespace at {
inline int get_num_threads() { return 1; }
template <class F>
void parallel_for(int64_t b, int64_t e, int64_t, const F& f) { if (b < e) f(b, e); }
}  // namespace at
