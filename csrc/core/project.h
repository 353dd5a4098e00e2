// The per-Gaussian projection stage (forward and VJP), shared by the backends: the CPU runs it
// in a parallel loop, the CUDA kernels once per thread. Pure composition of core/math.h.
#pragma once

#include "params.h"

namespace gsw {

template <typename T>
GSW_HD Vec3<T> load_vec3(const T* p) {
  return {p[0], p[1], p[2]};
}

// Values per Gaussian in ProjectParams::sh: 3 K SH coefficients, or 3 direct colours.
template <typename T>
GSW_HD int sh_values(const ProjectParams<T>& p) {
  return p.sh_degree >= 0 ? 3 * p.K : 3;
}

// Projects Gaussian i into p.cam and writes its outputs (zeros and radius 0 when culled).
// `degree` is the active SH degree (-1: direct colours); backends may pass a compile-time value.
// `sh_i` holds the Gaussian's coefficients (or colours), at least the active ones: by default
// p.sh + i * sh_values(p), or a copy in registers.
template <typename T>
GSW_HD void project_gaussian(const ProjectParams<T>& p, int64_t i, int degree, const T* sh_i) {
  const Camera<T>& cam = p.cam;
  T* m2 = p.means2d + 2 * i;
  T* cn = p.conics + 3 * i;
  T* col = p.colors + 3 * i;
  const Vec3<T> mean = load_vec3(p.means + 3 * i);
  const Vec3<T> pc = world_to_cam(cam, mean);
  const T opacity = sigmoid(p.opacity_logits[i]);
  Sym2<T> conic = {T(0), T(0), T(0)};
  Projection<T> proj;
  int radius = 0;
  if (pc.z > T(NEAR_PLANE)) {
    const Mat3<T> cov = cov_world_to_cam(cam, covariance_3d(p.quats + 4 * i, p.log_scales + 3 * i));
    proj = project_ewa(cam, pc, cov, ewa_jacobian(cam, pc));
    T det;
    if (conic_from_cov2d(proj.cov2d, conic, det)) {
      radius = footprint_radius(proj.cov2d, det, opacity);
      const int tx = (cam.width + TILE_SIZE - 1) / TILE_SIZE;
      const int ty = (cam.height + TILE_SIZE - 1) / TILE_SIZE;
      int x0, y0, x1, y1;
      if (radius > 0 && tile_rect(proj.mean2d, radius, tx, ty, x0, y0, x1, y1) == 0) radius = 0;
    }
  }
  p.radii[i] = radius;
  if (radius <= 0) {
    m2[0] = m2[1] = cn[0] = cn[1] = cn[2] = col[0] = col[1] = col[2] = T(0);
    p.depths[i] = p.opacities[i] = T(0);
    return;
  }
  m2[0] = proj.mean2d.x;
  m2[1] = proj.mean2d.y;
  cn[0] = conic.a;
  cn[1] = conic.b;
  cn[2] = conic.c;
  p.depths[i] = pc.z;
  p.opacities[i] = opacity;
  if (degree >= 0) {
    const Vec3<T> center = camera_center(cam);
    const Vec3<T> dir = {mean.x - center.x, mean.y - center.y, mean.z - center.z};
    const Vec3<T> c = sh_to_color(degree, dir, sh_i);
    col[0] = c.x;
    col[1] = c.y;
    col[2] = c.z;
  } else {
    for (int k = 0; k < 3; ++k) col[k] = sh_i[k];
  }
}

// Names of the bits of ProjectParams::nonfinite (bit k: kNonFiniteFields[k]), as the
// Gaussians' fields are called in Python.
constexpr int kNumNonFiniteFields = 5;
constexpr const char* kNonFiniteFields[kNumNonFiniteFields] = {"means", "quats", "log_scales",
                                                               "opacity_logits", "sh"};

constexpr int32_t kNonFiniteSh = 1 << 4;

// Bitmask of the geometry inputs of Gaussian i (means, quats, log_scales, opacity_logits) that
// hold NaN or Inf (bit k: kNonFiniteFields[k]).
template <typename T>
GSW_HD int32_t nonfinite_geometry(const ProjectParams<T>& p, int64_t i) {
  return (all_finite(p.means + 3 * i, 3) ? 0 : 1) | (all_finite(p.quats + 4 * i, 4) ? 0 : 2) |
         (all_finite(p.log_scales + 3 * i, 3) ? 0 : 4) | (all_finite(p.opacity_logits + i, 1) ? 0 : 8);
}

// Bitmask of all inputs of Gaussian i that hold NaN or Inf. Every stored value is checked:
// culled Gaussians and SH coefficients above the active degree too; with direct colours
// (sh_degree -1) the "sh" bit means the colours.
template <typename T>
GSW_HD int32_t nonfinite_fields(const ProjectParams<T>& p, int64_t i) {
  const int n = sh_values(p);
  return nonfinite_geometry(p, i) | (all_finite(p.sh + int64_t(n) * i, n) ? 0 : kNonFiniteSh);
}

// VJP of project_gaussian for everything but the colour: writes the cotangents of the
// quaternion, log-scales and opacity logit of a visible Gaussian i and returns the cotangent of
// its world mean from the geometry (the colour's view-direction term is added by the caller).
// Reads the inputs and p.radii only: the projection's other outputs are recomputed, so a render
// keeps none of them for this VJP once the blending's backward is done.
template <typename T>
GSW_HD Vec3<T> project_gaussian_vjp_geometry(const ProjectParams<T>& p, const ProjectGradParams<T>& g,
                                             int64_t i) {
  const Camera<T>& cam = p.cam;
  const T* quat = p.quats + 4 * i;
  const T* log_scale = p.log_scales + 3 * i;
  const Vec3<T> pc = world_to_cam(cam, load_vec3(p.means + 3 * i));
  const Mat3<T> cov = cov_world_to_cam(cam, covariance_3d(quat, log_scale));
  // The conic and the opacity are recomputed (as the forward did), not kept from the forward.
  const EwaJacobian<T> J = ewa_jacobian(cam, pc);
  Sym2<T> conic;
  T det;
  conic_from_cov2d(project_ewa(cam, pc, cov, J).cov2d, conic, det);
  const T* vc = g.v_conics + 3 * i;
  const Sym2<T> v_cov2d = conic_from_cov2d_vjp(conic, Sym2<T>{vc[0], vc[1], vc[2]});
  const Vec2<T> v_mean2d = {g.v_means2d[2 * i], g.v_means2d[2 * i + 1]};
  Vec3<T> v_pc = {T(0), T(0), g.v_depths[i]};
  Mat3<T> v_cov = mat3_zero<T>();
  project_ewa_vjp(cam, pc, cov, J, v_mean2d, v_cov2d, v_pc, v_cov);
  T vq[4] = {T(0), T(0), T(0), T(0)};
  T vls[3] = {T(0), T(0), T(0)};
  covariance_3d_vjp(quat, log_scale, cov_world_to_cam_vjp(cam, v_cov), vq, vls);
  for (int k = 0; k < 4; ++k) g.v_quats[4 * i + k] = vq[k];
  for (int k = 0; k < 3; ++k) g.v_log_scales[3 * i + k] = vls[k];
  g.v_opacity_logits[i] = sigmoid_vjp(sigmoid(p.opacity_logits[i]), g.v_opacities[i]);
  return world_to_cam_vjp(cam, v_pc);
}

// Zero cotangents of a culled Gaussian i (`coeffs` SH values per Gaussian).
template <typename T>
GSW_HD void zero_gaussian_grads(const ProjectGradParams<T>& g, int64_t i, int coeffs) {
  for (int k = 0; k < 3; ++k) g.v_means[3 * i + k] = g.v_log_scales[3 * i + k] = T(0);
  for (int k = 0; k < 4; ++k) g.v_quats[4 * i + k] = T(0);
  for (int k = 0; k < coeffs; ++k) g.v_sh[int64_t(coeffs) * i + k] = T(0);
  g.v_opacity_logits[i] = T(0);
}

}  // namespace gsw
