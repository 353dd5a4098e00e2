// CUDA projection stage: one thread per Gaussian, EWA projection + culling + footprint + SH
// colour fused in one kernel (and its VJP in one kernel). The per-Gaussian code is the CPU
// backend's, calling the same core/math.h functions; the SH degree is a template parameter so
// the basis arrays stay in registers.
#include "cuda/common.cuh"

namespace gsw::cuda {

namespace {

constexpr int kThreads = 256;

template <typename T>
__device__ __forceinline__ Vec3<T> load3(const T* p) {
  return {p[0], p[1], p[2]};
}

template <typename T, int DEG>
__global__ void __launch_bounds__(kThreads) project_forward_kernel(const ProjectParams<T> p) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= p.N) return;
  const Camera<T>& cam = p.cam;
  T* m2 = p.means2d + 2 * i;
  T* cn = p.conics + 3 * i;
  T* col = p.colors + 3 * i;
  auto cull = [&]() {
    p.radii[i] = 0;
    m2[0] = m2[1] = T(0);
    cn[0] = cn[1] = cn[2] = T(0);
    col[0] = col[1] = col[2] = T(0);
    p.depths[i] = T(0);
    p.opacities[i] = T(0);
  };
  const Vec3<T> mean = load3(p.means + 3 * i);
  const Vec3<T> pc = world_to_cam(cam, mean);
  if (!(pc.z > T(NEAR_PLANE))) return cull();
  const Mat3<T> cov =
      cov_world_to_cam(cam, covariance_3d(p.quats + 4 * i, p.log_scales + 3 * i));
  const Projection<T> proj = project_ewa(cam, pc, cov);
  Sym2<T> conic;
  T det;
  if (!conic_from_cov2d(proj.cov2d, conic, det)) return cull();
  const int radius = footprint_radius(proj.cov2d, det);
  const int tx = (cam.width + TILE_SIZE - 1) / TILE_SIZE;
  const int ty = (cam.height + TILE_SIZE - 1) / TILE_SIZE;
  int x0, y0, x1, y1;
  if (radius <= 0 || tile_rect(proj.mean2d, radius, tx, ty, x0, y0, x1, y1) == 0) return cull();

  p.radii[i] = radius;
  m2[0] = proj.mean2d.x;
  m2[1] = proj.mean2d.y;
  cn[0] = conic.a;
  cn[1] = conic.b;
  cn[2] = conic.c;
  p.depths[i] = pc.z;
  p.opacities[i] = sigmoid(p.opacity_logits[i]);
  if (DEG >= 0) {
    const Vec3<T> center = camera_center(cam);
    const Vec3<T> dir = {mean.x - center.x, mean.y - center.y, mean.z - center.z};
    const Vec3<T> c = sh_to_color(DEG, dir, p.sh + int64_t(3) * p.K * i);
    col[0] = c.x;
    col[1] = c.y;
    col[2] = c.z;
  } else {
    col[0] = p.sh[3 * i];
    col[1] = p.sh[3 * i + 1];
    col[2] = p.sh[3 * i + 2];
  }
}

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
__global__ void __launch_bounds__(kThreads)
    project_backward_kernel(const ProjectParams<T> p, const ProjectGradParams<T> g) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= p.N) return;
  const Camera<T>& cam = p.cam;
  const int coeffs = DEG >= 0 ? 3 * p.K : 3;
  T* v_mean = g.v_means + 3 * i;
  T* v_quat = g.v_quats + 4 * i;
  T* v_ls = g.v_log_scales + 3 * i;
  T* v_sh = g.v_sh + int64_t(coeffs) * i;
  if (p.radii[i] <= 0) {
    for (int k = 0; k < 3; ++k) v_mean[k] = v_ls[k] = T(0);
    for (int k = 0; k < 4; ++k) v_quat[k] = T(0);
    for (int k = 0; k < coeffs; ++k) v_sh[k] = T(0);
    g.v_opacity_logits[i] = T(0);
    return;
  }
  const T* quat = p.quats + 4 * i;
  const T* log_scale = p.log_scales + 3 * i;
  const Vec3<T> mean = load3(p.means + 3 * i);
  const Vec3<T> pc = world_to_cam(cam, mean);
  const Mat3<T> cov = cov_world_to_cam(cam, covariance_3d(quat, log_scale));
  const T* cn = p.conics + 3 * i;
  const Sym2<T> conic = {cn[0], cn[1], cn[2]};
  const T* vc = g.v_conics + 3 * i;
  const Sym2<T> v_cov2d = conic_from_cov2d_vjp(conic, Sym2<T>{vc[0], vc[1], vc[2]});
  const Vec2<T> v_mean2d = {g.v_means2d[2 * i], g.v_means2d[2 * i + 1]};

  Vec3<T> v_pc = {T(0), T(0), g.v_depths[i]};
  Mat3<T> v_cov = mat3_zero<T>();
  project_ewa_vjp(cam, pc, cov, v_mean2d, v_cov2d, v_pc, v_cov);
  Vec3<T> v_world = world_to_cam_vjp(cam, v_pc);
  T vq[4] = {T(0), T(0), T(0), T(0)};
  T vls[3] = {T(0), T(0), T(0)};
  covariance_3d_vjp(quat, log_scale, cov_world_to_cam_vjp(cam, v_cov), vq, vls);
  for (int k = 0; k < 4; ++k) v_quat[k] = vq[k];
  for (int k = 0; k < 3; ++k) v_ls[k] = vls[k];
  g.v_opacity_logits[i] = sigmoid_vjp(p.opacities[i], g.v_opacities[i]);

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
    const Vec3<T> center = camera_center(cam);
    const Vec3<T> dir = {mean.x - center.x, mean.y - center.y, mean.z - center.z};
    const T* col = p.colors + 3 * i;
    const Vec3<T> v_dir = sh_to_color_vjp(DEG, dir, shl, Vec3<T>{col[0], col[1], col[2]},
                                          Vec3<T>{v_col[0], v_col[1], v_col[2]}, vs);
    v_world.x += v_dir.x;
    v_world.y += v_dir.y;
    v_world.z += v_dir.z;
    store_coeffs<T, 3 * KD>(v_sh, vs, vec);
    for (int k = 3 * KD; k < coeffs; ++k) v_sh[k] = T(0);  // coefficients above the degree
  } else {
    for (int k = 0; k < 3; ++k) v_sh[k] = v_col[k];
  }
  v_mean[0] = v_world.x;
  v_mean[1] = v_world.y;
  v_mean[2] = v_world.z;
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
