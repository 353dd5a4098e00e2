// Helpers shared by the CUDA kernels of gsw: stream, temporary buffers, launch checks, warp
// reductions. No rasterizer math here (that lives in core/math.h, shared with the CPU).
#pragma once

#include <c10/cuda/CUDACachingAllocator.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAStream.h>
#include <cuda_runtime.h>

#include <cub/device/device_scan.cuh>

#include <cstdint>

#include "cuda/backend_cuda.h"

namespace gsw::cuda {

inline cudaStream_t current_stream() { return c10::cuda::getCurrentCUDAStream().stream(); }

// Device buffer from torch's caching allocator (stream-ordered on the current stream, freed on
// scope exit).
struct DeviceBuffer {
  c10::DataPtr ptr;
  explicit DeviceBuffer(size_t bytes)
      : ptr(c10::cuda::CUDACachingAllocator::get()->allocate(bytes > 0 ? bytes : 1)) {}
  template <typename U>
  U* as() const {
    return static_cast<U*>(ptr.get());
  }
};

#define GSW_CUDA_CHECK(expr) C10_CUDA_CHECK(expr)
#define GSW_KERNEL_CHECK() C10_CUDA_KERNEL_LAUNCH_CHECK()

// Exclusive prefix sum of n int32 values on `stream`: cub's scratch-size query, a scratch buffer from
// the caching allocator, the scan. `in` and `out` may not alias.
inline void exclusive_sum(const int32_t* in, int32_t* out, int n, cudaStream_t stream) {
  size_t bytes = 0;
  GSW_CUDA_CHECK(cub::DeviceScan::ExclusiveSum(nullptr, bytes, in, out, n, stream));
  DeviceBuffer temp(bytes);
  GSW_CUDA_CHECK(cub::DeviceScan::ExclusiveSum(temp.as<void>(), bytes, in, out, n, stream));
}

inline unsigned blocks_for(int64_t n, int threads) {
  return static_cast<unsigned>((n + threads - 1) / threads);
}

constexpr unsigned kFullMask = 0xffffffffu;

template <typename U>
__device__ __forceinline__ U warp_sum(U v) {
#pragma unroll
  for (int o = 16; o > 0; o >>= 1) v += __shfl_down_sync(kFullMask, v, o);
  return v;
}
template <typename U>
__device__ __forceinline__ U warp_max(U v) {
#pragma unroll
  for (int o = 16; o > 0; o >>= 1) {
    const U w = __shfl_down_sync(kFullMask, v, o);
    v = w > v ? w : v;
  }
  return v;
}

// Transposed butterfly: the warp sums of N per-lane values in about N + 2 shuffles instead of
// 5 N (N = 3: 6 instead of 15; N = 10: 12 instead of 50). Each step (lane offsets 16, 8, 4, 2)
// halves the values a lane carries: of each pair (v[i], v[H + i]), H = ceil(n / 2), the lane
// whose offset bit is 0 keeps v[i] and the other v[H + i] (a missing v[H + i] counts as 0), each
// adding its partner's copy of what it keeps; a lone value (n = 1) is summed whole, as the last
// step (offset 1) always is. Afterwards every lane holds the warp sum of one value, returned with
// its index in `index` (-1: this lane holds a padding 0); lanes 2l and 2l + 1 share one. N = 3:
// lanes 0-7 hold sum(v[0]), 8-15 sum(v[1]), 16-23 sum(v[2]), 24-31 padding. N = 10: lanes 0-5
// hold sum(v[0..2]), 8-11 sum(v[3..4]), 16-21 sum(v[5..7]), 24-27 sum(v[8..9]) (two lanes each),
// the others padding.
template <int O, int N, typename U>
__device__ __forceinline__ U warp_sum_transposed_step(const U (&v)[N], int lane, int& index,
                                                      int& count) {
  if constexpr (N == 1) {
    const U x = v[0] + __shfl_xor_sync(kFullMask, v[0], O);
    if constexpr (O == 1) {
      return x;
    } else {
      const U w[1] = {x};
      return warp_sum_transposed_step<O / 2>(w, lane, index, count);
    }
  } else {
    static_assert(O > 1, "more values than the warp's steps can halve");
    constexpr int H = (N + 1) / 2;
    const bool hi = lane & O;
    U w[H];
#pragma unroll
    for (int i = 0; i < H; ++i) {
      const U lo_v = v[i], hi_v = H + i < N ? v[H + i] : U(0);
      w[i] = (hi ? hi_v : lo_v) + __shfl_xor_sync(kFullMask, hi ? lo_v : hi_v, O);
    }
    // This lane's values are now v[index .. index + count) (count <= 0: padding only).
    if (hi) {
      index += H;
      count -= H;
    } else {
      count = count < H ? count : H;
    }
    return warp_sum_transposed_step<O / 2>(w, lane, index, count);
  }
}
template <int N, typename U>
__device__ __forceinline__ U warp_sum_transposed(const U (&v)[N], int& index) {
  static_assert(N >= 1 && N <= 16, "one to 16 values");
  index = 0;
  int count = N;
  const U x = warp_sum_transposed_step<16>(v, static_cast<int>(threadIdx.x & 31), index, count);
  if (count <= 0) index = -1;
  return x;
}

// Max over the warp of non-negative values, valid in lane 0. The bit patterns of non-negative
// floats order like unsigned integers: one integer reduction for float (sm_80+); double: shuffles.
__device__ __forceinline__ float warp_max_nonneg(float v) {
  return __uint_as_float(__reduce_max_sync(kFullMask, __float_as_uint(v)));
}
__device__ __forceinline__ double warp_max_nonneg(double v) { return warp_max(v); }

// atomicMax for non-negative floating-point values (same bit-pattern order).
__device__ __forceinline__ void atomic_max_nonneg(float* addr, float v) {
  atomicMax(reinterpret_cast<int*>(addr), __float_as_int(v));
}
__device__ __forceinline__ void atomic_max_nonneg(double* addr, double v) {
  atomicMax(reinterpret_cast<unsigned long long*>(addr),
            static_cast<unsigned long long>(__double_as_longlong(v)));
}

}  // namespace gsw::cuda
