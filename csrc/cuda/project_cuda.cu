// CUDA projection stage: one thread per Gaussian, EWA projection + culling + footprint + SH
// colour fused in one kernel (and its VJP in one kernel), running the shared per-Gaussian code
// of core/project.h; the SH degree is a template parameter so the basis arrays stay in
// registers, and the SH cotangents move through registers with 128-bit accesses.
#include "core/project.h"
#include "cuda/common.cuh"

namespace gsw::cuda {

namespace {

constexpr int kThreads = 256;

// 128-bit moves of per-Gaussian coefficient arrays (float32 only).
template <typename T>
struct VecIO {
  static constexpr bool kOk = false;
};
template <>
struct VecIO<float> {
  static constexpr bool kOk = true;
};

template <typename T, int n>
__device__ __forceinline__ void load_coeffs(const T* src, T* dst, bool vec) {
  if constexpr (VecIO<T>::kOk && n % 4 == 0) {
    if (vec) {
#pragma unroll
      for (int k = 0; k < n; k += 4) {
        const float4 v = *reinterpret_cast<const float4*>(src + k);
        dst[k] = v.x;
        dst[k + 1] = v.y;
        dst[k + 2] = v.z;
        dst[k + 3] = v.w;
      }
      return;
    }
  }
#pragma unroll
  for (int k = 0; k < n; ++k) dst[k] = src[k];
}
template <typename T, int n>
__device__ __forceinline__ void store_coeffs(T* dst, const T* src, bool vec) {
  if constexpr (VecIO<T>::kOk && n % 4 == 0) {
    if (vec) {
#pragma unroll
      for (int k = 0; k < n; k += 4)
        *reinterpret_cast<float4*>(dst + k) = make_float4(src[k], src[k + 1], src[k + 2], src[k + 3]);
      return;
    }
  }
#pragma unroll
  for (int k = 0; k < n; ++k) dst[k] = src[k];
}

template <typename T, int DEG>
__global__ void __launch_bounds__(kThreads) project_forward_kernel(const ProjectParams<T> p) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= p.N) return;
  const int n = sh_values(p);
  const T* sh_i = p.sh + int64_t(n) * i;
  // The active coefficients pass through registers, with 128-bit loads in float32: faster than the
  // colour's scalar reads of global memory (a lane's 48 coefficients span 192 bytes), even though
  // culled Gaussians load them too (BENCHMARKS.md 2h); the validation checks the same registers.
  constexpr int KA = DEG >= 0 ? 3 * (DEG + 1) * (DEG + 1) : 3;
  const bool vec = VecIO<T>::kOk && n % 4 == 0 && reinterpret_cast<uintptr_t>(p.sh) % 16 == 0;
  T shl[KA];
  load_coeffs<T, KA>(sh_i, shl, vec);
  project_gaussian(p, i, DEG, shl);
  if (!p.nonfinite) return;
  // Validation: flag, never synchronise (the binning reads the flags back).
  const bool sh_ok = all_finite(shl, KA) && all_finite(sh_i + KA, n - KA);
  const int32_t bad = nonfinite_geometry(p, i) | (sh_ok ? 0 : kNonFiniteSh);
  if (bad) atomicOr(p.nonfinite, bad);
}

template <typename T, int DEG>
__global__ void __launch_bounds__(kThreads)
    project_backward_kernel(const ProjectParams<T> p, const ProjectGradParams<T> g) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= p.N) return;
  const int coeffs = DEG >= 0 ? 3 * p.K : 3;
  if (p.radii[i] <= 0) {
    zero_gaussian_grads(g, i, coeffs);
    return;
  }
  T* v_sh = g.v_sh + int64_t(coeffs) * i;
  const Vec3<T> mean = load_vec3(p.means + 3 * i);
  Vec3<T> v_world = project_gaussian_vjp_geometry(p, g, i);
  const T* v_col = g.v_colors + 3 * i;
  if (DEG >= 0) {
    constexpr int KD = DEG >= 0 ? (DEG + 1) * (DEG + 1) : 1;
    // This Gaussian's coefficients and their cotangents go through registers, moved with
    // 128-bit accesses where the layout allows (float32, 3 K divisible by 4).
    const T* sh_i = p.sh + int64_t(3) * p.K * i;
    const bool vec = VecIO<T>::kOk && (coeffs % 4 == 0) &&
                     ((reinterpret_cast<uintptr_t>(p.sh) | reinterpret_cast<uintptr_t>(g.v_sh)) % 16 == 0);
    T shl[3 * KD], vs[3 * KD];
    load_coeffs<T, 3 * KD>(sh_i, shl, vec);
#pragma unroll
    for (int k = 0; k < 3 * KD; ++k) vs[k] = T(0);
    const Vec3<T> center = camera_center(p.cam);
    const Vec3<T> dir = {mean.x - center.x, mean.y - center.y, mean.z - center.z};
    const Vec3<T> v_dir = sh_to_color_vjp(DEG, dir, shl, Vec3<T>{v_col[0], v_col[1], v_col[2]}, vs);
    v_world.x += v_dir.x;
    v_world.y += v_dir.y;
    v_world.z += v_dir.z;
    store_coeffs<T, 3 * KD>(v_sh, vs, vec);
    for (int k = 3 * KD; k < coeffs; ++k) v_sh[k] = T(0);  // coefficients above the degree
  } else {
    for (int k = 0; k < 3; ++k) v_sh[k] = v_col[k];
  }
  g.v_means[3 * i] = v_world.x;
  g.v_means[3 * i + 1] = v_world.y;
  g.v_means[3 * i + 2] = v_world.z;
}

template <typename T, typename F>
void dispatch_degree(int degree, F&& f) {
  switch (degree) {
    case -1: f(std::integral_constant<int, -1>{}); break;
    case 0: f(std::integral_constant<int, 0>{}); break;
    case 1: f(std::integral_constant<int, 1>{}); break;
    case 2: f(std::integral_constant<int, 2>{}); break;
    default: f(std::integral_constant<int, 3>{}); break;
  }
}

}  // namespace

template <typename T>
void project_forward(const ProjectParams<T>& p) {
  if (p.N <= 0) return;
  dispatch_degree<T>(p.sh_degree, [&](auto deg) {
    project_forward_kernel<T, decltype(deg)::value>
        <<<blocks_for(p.N, kThreads), kThreads, 0, current_stream()>>>(p);
  });
  GSW_KERNEL_CHECK();
}

template <typename T>
void project_backward(const ProjectParams<T>& p, const ProjectGradParams<T>& g) {
  if (p.N <= 0) return;
  dispatch_degree<T>(p.sh_degree, [&](auto deg) {
    project_backward_kernel<T, decltype(deg)::value>
        <<<blocks_for(p.N, kThreads), kThreads, 0, current_stream()>>>(p, g);
  });
  GSW_KERNEL_CHECK();
}

template void project_forward<float>(const ProjectParams<float>&);
template void project_forward<double>(const ProjectParams<double>&);
template void project_backward<float>(const ProjectParams<float>&, const ProjectGradParams<float>&);
template void project_backward<double>(const ProjectParams<double>&,
                                       const ProjectGradParams<double>&);

}  // namespace gsw::cuda
