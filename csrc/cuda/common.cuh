// Helpers shared by the CUDA kernels of gsw: stream, temporary buffers, launch checks, warp
// reductions. No rasterizer math here (that lives in core/math.h, shared with the CPU).
#pragma once

#include <c10/cuda/CUDACachingAllocator.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAStream.h>
#include <cuda_runtime.h>

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

// Transposed butterfly: three sums over the warp in 6 shuffles instead of 15 (each step keeps
// half of the quantities and trades the other half). Afterwards lanes 0-7 hold sum(s0), 8-15
// sum(s1) and 16-23 sum(s2) (24-31: sum(s1) again).
template <typename U>
__device__ __forceinline__ U warp_sum3(U s0, U s1, U s2) {
  const int lane = threadIdx.x & 31;
  const bool h16 = lane & 16, h8 = lane & 8;
  // Lanes 0-15 keep s0 and s1, lanes 16-31 s2 (and s1).
  const U a = (h16 ? s2 : s0) + __shfl_xor_sync(kFullMask, h16 ? s0 : s2, 16);
  const U b = s1 + __shfl_xor_sync(kFullMask, s1, 16);
  // Lanes 0-7 and 16-23 keep a, 8-15 and 24-31 b.
  U x = (h8 ? b : a) + __shfl_xor_sync(kFullMask, h8 ? a : b, 8);
#pragma unroll
  for (int o = 4; o > 0; o >>= 1) x += __shfl_xor_sync(kFullMask, x, o);
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
