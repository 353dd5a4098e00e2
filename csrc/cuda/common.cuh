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

// atomicMax for non-negative floating-point values (their bit patterns order like integers).
// Transposed butterfly reductions: several quantities reduced over the warp with fewer shuffles
// than one reduction each (each step keeps half of the quantities and trades the other half).
// warp_sum3_max: 6 shuffles; afterwards lanes 0-7 hold sum(s0), 8-15 sum(s1), 16-23 sum(s2) and
// 24-31 max(m).
template <typename U>
__device__ __forceinline__ U warp_sum3_max(U s0, U s1, U s2, U m) {
  const int lane = threadIdx.x & 31;
  const bool h16 = lane & 16, h8 = lane & 8;
  U a = h16 ? s2 : s0, b = h16 ? m : s1;
  const U ra = __shfl_xor_sync(kFullMask, h16 ? s0 : s2, 16);
  const U rb = __shfl_xor_sync(kFullMask, h16 ? s1 : m, 16);
  a += ra;
  b = h16 ? (rb > b ? rb : b) : b + rb;
  const bool is_max = h16 && h8;
  U x = h8 ? b : a;
  U r = __shfl_xor_sync(kFullMask, h8 ? a : b, 8);
  x = is_max ? (r > x ? r : x) : x + r;
#pragma unroll
  for (int o = 4; o > 0; o >>= 1) {
    r = __shfl_xor_sync(kFullMask, x, o);
    x = is_max ? (r > x ? r : x) : x + r;
  }
  return x;
}
// warp_sum1_max: 5 shuffles; afterwards lanes 0-15 hold sum(s0) and 16-31 max(m).
template <typename U>
__device__ __forceinline__ U warp_sum1_max(U s0, U m) {
  const bool is_max = threadIdx.x & 16;
  U x = is_max ? m : s0;
  U r = __shfl_xor_sync(kFullMask, is_max ? s0 : m, 16);
  x = is_max ? (r > x ? r : x) : x + r;
#pragma unroll
  for (int o = 8; o > 0; o >>= 1) {
    r = __shfl_xor_sync(kFullMask, x, o);
    x = is_max ? (r > x ? r : x) : x + r;
  }
  return x;
}

__device__ __forceinline__ void atomic_max_nonneg(float* addr, float v) {
  atomicMax(reinterpret_cast<int*>(addr), __float_as_int(v));
}
__device__ __forceinline__ void atomic_max_nonneg(double* addr, double v) {
  atomicMax(reinterpret_cast<unsigned long long*>(addr),
            static_cast<unsigned long long>(__double_as_longlong(v)));
}

}  // namespace gsw::cuda
