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
__device__ __forceinline__ void atomic_max_nonneg(float* addr, float v) {
  atomicMax(reinterpret_cast<int*>(addr), __float_as_int(v));
}
__device__ __forceinline__ void atomic_max_nonneg(double* addr, double v) {
  atomicMax(reinterpret_cast<unsigned long long*>(addr),
            static_cast<unsigned long long>(__double_as_longlong(v)));
}

}  // namespace gsw::cuda
