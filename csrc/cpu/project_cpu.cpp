// CPU projection stage: the shared per-Gaussian code of core/project.h over all Gaussians.
//
// The per-Gaussian loops are tile kernels (cpu/parallel.h) with everything they call inlined
// (flatten): core/project.h's functions are compiled into each clone, so the x86-64-v3 clone
// runs the projection and SH arithmetic with FMA and AVX2.
#include "core/project.h"
#include "cpu/backend_cpu.h"
#include "cpu/parallel.h"

namespace gsw::cpu {

namespace {

template <typename T>
GSW_CPU_KERNEL GSW_CPU_FLATTEN void project_range(const ProjectParams<T>& p, int64_t i0, int64_t i1) {
  const int n = sh_values(p);
  for (int64_t i = i0; i < i1; ++i) {
    project_gaussian(p, i, p.sh_degree, p.sh + int64_t(n) * i);
    if (p.nonfinite) {
      const int32_t bad = nonfinite_fields(p, i);
      if (bad) __atomic_fetch_or(p.nonfinite, bad, __ATOMIC_RELAXED);
    }
  }
}

template <typename T>
GSW_CPU_KERNEL GSW_CPU_FLATTEN void project_backward_range(const ProjectParams<T>& p, const ProjectGradParams<T>& g,
                                                           int64_t i0, int64_t i1) {
  const Vec3<T> center = camera_center(p.cam);
  const int coeffs = p.sh_degree >= 0 ? 3 * p.K : 3;
  for (int64_t i = i0; i < i1; ++i) {
    zero_gaussian_grads(g, i, coeffs);
    if (p.radii[i] <= 0) continue;
    Vec3<T> v_world = project_gaussian_vjp_geometry(p, g, i);
    const T* v_col = g.v_colors + 3 * i;
    T* v_sh = g.v_sh + int64_t(coeffs) * i;
    if (p.sh_degree >= 0) {
      const Vec3<T> mean = load_vec3(p.means + 3 * i);
      const Vec3<T> dir = {mean.x - center.x, mean.y - center.y, mean.z - center.z};
      const Vec3<T> v_dir = sh_to_color_vjp(p.sh_degree, dir, p.sh + int64_t(3) * p.K * i,
                                            Vec3<T>{v_col[0], v_col[1], v_col[2]}, v_sh);
      v_world.x += v_dir.x;
      v_world.y += v_dir.y;
      v_world.z += v_dir.z;
    } else {
      for (int k = 0; k < 3; ++k) v_sh[k] = v_col[k];
    }
    g.v_means[3 * i] = v_world.x;
    g.v_means[3 * i + 1] = v_world.y;
    g.v_means[3 * i + 2] = v_world.z;
  }
}

}  // namespace

template <typename T>
void project_forward(const ProjectParams<T>& p) {
  parallel_ranges(p.N, [&](int64_t i0, int64_t i1) { project_range(p, i0, i1); });
}

template <typename T>
void project_backward(const ProjectParams<T>& p, const ProjectGradParams<T>& g) {
  parallel_ranges(p.N, [&](int64_t i0, int64_t i1) { project_backward_range(p, g, i0, i1); });
}

template void project_forward<float>(const ProjectParams<float>&);
template void project_forward<double>(const ProjectParams<double>&);
template void project_backward<float>(const ProjectParams<float>&, const ProjectGradParams<float>&);
template void project_backward<double>(const ProjectParams<double>&, const ProjectGradParams<double>&);

}  // namespace gsw::cpu
