// gsw rasterizer math core: torch-free, header-only, shared by the CPU and CUDA backends.
//
// Every forward function is followed by its vector-Jacobian product (VJP), named `*_vjp`;
// cotangents are named `v_<x>`. All functions are templated on the scalar type so the
// CPU backend can instantiate them in float32 and float64 (for gradcheck).
//
// Conventions (INRIA 3DGS compatible, see ../shared/GUIDE.md section 3):
//  * quaternions are (w, x, y, z), unnormalised; scales are log-scales; opacity is a logit;
//  * cameras are world-to-camera, OpenCV axes (x right, y down, z forward);
//  * the projected mean is K p (pixel (i, j) has its centre at (i + 0.5, j + 0.5) in that frame,
//    which equals the INRIA rasterizer for cx = W / 2, cy = H / 2);
//  * 2x2 symmetric matrices are stored (a, b, c) = [[a, b], [b, c]]; a cotangent of such a
//    triple is the derivative w.r.t. the three free parameters (b counted once).
#pragma once

#include <cmath>
#include <cstdint>

#include "constants.h"

#if defined(__CUDACC__)
#define GSW_HD __host__ __device__ __forceinline__
#define GSW_UNROLL _Pragma("unroll")
#else
#define GSW_HD inline
#define GSW_UNROLL
#endif

namespace gsw {

#if !defined(__CUDACC__)
// Host code: pick the float / double overloads (CUDA provides them globally).
using std::ceil;
using std::exp;
using std::floor;
using std::log;
using std::sqrt;
#endif

// Element type of T: T itself for scalars. The CPU backend specialises it for GCC vector types
// (cpu/simd.h), so the per-pixel blending functions below (written with Scalar<T> constants and
// ternaries, which GCC applies lane by lane to vectors) also run on whole lane blocks.
template <typename T>
struct ScalarOf {
  using type = T;
};
template <typename T>
using Scalar = typename ScalarOf<T>::type;

// ------------------------------------------------------------------ small linear algebra

template <typename T>
struct Vec2 {
  T x, y;
};
template <typename T>
struct Vec3 {
  T x, y, z;
};
// 3x3 matrix, row-major m[r][c].
template <typename T>
struct Mat3 {
  T m[3][3];
};
// 2x2 symmetric matrix [[a, b], [b, c]].
template <typename T>
struct Sym2 {
  T a, b, c;
};

template <typename T>
GSW_HD Mat3<T> mat3_zero() {
  Mat3<T> r;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) r.m[i][j] = T(0);
  return r;
}

template <typename T>
GSW_HD Mat3<T> matmul(const Mat3<T>& a, const Mat3<T>& b) {
  Mat3<T> r;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      r.m[i][j] = a.m[i][0] * b.m[0][j] + a.m[i][1] * b.m[1][j] + a.m[i][2] * b.m[2][j];
  return r;
}

template <typename T>
GSW_HD Mat3<T> transpose(const Mat3<T>& a) {
  Mat3<T> r;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) r.m[i][j] = a.m[j][i];
  return r;
}

// a * b^T
template <typename T>
GSW_HD Mat3<T> matmul_bt(const Mat3<T>& a, const Mat3<T>& b) {
  return matmul(a, transpose(b));
}

// a^T * b
template <typename T>
GSW_HD Mat3<T> matmul_at(const Mat3<T>& a, const Mat3<T>& b) {
  return matmul(transpose(a), b);
}

template <typename T>
GSW_HD Vec3<T> matvec(const Mat3<T>& a, const Vec3<T>& v) {
  return {a.m[0][0] * v.x + a.m[0][1] * v.y + a.m[0][2] * v.z,
          a.m[1][0] * v.x + a.m[1][1] * v.y + a.m[1][2] * v.z,
          a.m[2][0] * v.x + a.m[2][1] * v.y + a.m[2][2] * v.z};
}

// a^T v
template <typename T>
GSW_HD Vec3<T> matvec_t(const Mat3<T>& a, const Vec3<T>& v) {
  return {a.m[0][0] * v.x + a.m[1][0] * v.y + a.m[2][0] * v.z,
          a.m[0][1] * v.x + a.m[1][1] * v.y + a.m[2][1] * v.z,
          a.m[0][2] * v.x + a.m[1][2] * v.y + a.m[2][2] * v.z};
}

// ------------------------------------------------------------------ finite checks

// |v| as an unsigned bit pattern: ordered like |v|, and NaN / Inf lie at or above the pattern of
// infinity. Bitwise, so the check below holds under any fast-math flags.
GSW_HD uint32_t magnitude_bits(float v) {
#if defined(__CUDA_ARCH__)
  return __float_as_uint(v) & 0x7fffffffu;
#else
  uint32_t b;
  __builtin_memcpy(&b, &v, sizeof(b));
  return b & 0x7fffffffu;
#endif
}
GSW_HD uint64_t magnitude_bits(double v) {
#if defined(__CUDA_ARCH__)
  return static_cast<uint64_t>(__double_as_longlong(v)) & 0x7fffffffffffffffull;
#else
  uint64_t b;
  __builtin_memcpy(&b, &v, sizeof(b));
  return b & 0x7fffffffffffffffull;
#endif
}
GSW_HD uint32_t infinity_bits(float) { return 0x7f800000u; }
GSW_HD uint64_t infinity_bits(double) { return 0x7ff0000000000000ull; }

// Whether x[0..n) are all finite (no NaN, no +-Inf): one max over the magnitude patterns.
// Unrolled on the device when n is known, so x may be a register array.
template <typename T>
GSW_HD bool all_finite(const T* x, int n) {
  decltype(magnitude_bits(T(0))) m = 0;
  GSW_UNROLL
  for (int k = 0; k < n; ++k) {
    const auto b = magnitude_bits(x[k]);
    m = b > m ? b : m;
  }
  return m < infinity_bits(T(0));
}

// ------------------------------------------------------------------ activations

template <typename T>
GSW_HD T sigmoid(T x) {
  return T(1) / (T(1) + exp(-x));
}
// d sigmoid(x) / dx expressed with y = sigmoid(x).
template <typename T>
GSW_HD T sigmoid_vjp(T y, T v_y) {
  return v_y * y * (T(1) - y);
}

// ------------------------------------------------------------------ camera

// A pinhole camera: world-to-camera rotation R and translation t (OpenCV axes), intrinsics
// and image size.
template <typename T>
struct Camera {
  Mat3<T> R;
  Vec3<T> t;
  T fx, fy, cx, cy;
  int width, height;
};

// Camera centre in world coordinates, -R^T t.
template <typename T>
GSW_HD Vec3<T> camera_center(const Camera<T>& cam) {
  Vec3<T> c = matvec_t(cam.R, cam.t);
  return {-c.x, -c.y, -c.z};
}

// p_cam = R p + t.
template <typename T>
GSW_HD Vec3<T> world_to_cam(const Camera<T>& cam, const Vec3<T>& p) {
  Vec3<T> r = matvec(cam.R, p);
  return {r.x + cam.t.x, r.y + cam.t.y, r.z + cam.t.z};
}
template <typename T>
GSW_HD Vec3<T> world_to_cam_vjp(const Camera<T>& cam, const Vec3<T>& v_pc) {
  return matvec_t(cam.R, v_pc);
}

// Sigma_cam = R Sigma R^T.
template <typename T>
GSW_HD Mat3<T> cov_world_to_cam(const Camera<T>& cam, const Mat3<T>& cov) {
  return matmul_bt(matmul(cam.R, cov), cam.R);
}
// VJP with a symmetric cotangent: v_Sigma = R^T v_Sigma_cam R.
template <typename T>
GSW_HD Mat3<T> cov_world_to_cam_vjp(const Camera<T>& cam, const Mat3<T>& v_cov_cam) {
  return matmul(matmul_at(cam.R, v_cov_cam), cam.R);
}

// ------------------------------------------------------------------ 3-D covariance

// Rotation matrix of the normalised quaternion q / |q|, q = (w, x, y, z).
template <typename T>
GSW_HD Mat3<T> quat_to_rotmat(const T q_in[4]) {
  const T inv = T(1) / sqrt(q_in[0] * q_in[0] + q_in[1] * q_in[1] + q_in[2] * q_in[2] +
                            q_in[3] * q_in[3]);
  const T w = q_in[0] * inv, x = q_in[1] * inv, y = q_in[2] * inv, z = q_in[3] * inv;
  Mat3<T> r;
  r.m[0][0] = T(1) - T(2) * (y * y + z * z);
  r.m[0][1] = T(2) * (x * y - w * z);
  r.m[0][2] = T(2) * (x * z + w * y);
  r.m[1][0] = T(2) * (x * y + w * z);
  r.m[1][1] = T(1) - T(2) * (x * x + z * z);
  r.m[1][2] = T(2) * (y * z - w * x);
  r.m[2][0] = T(2) * (x * z - w * y);
  r.m[2][1] = T(2) * (y * z + w * x);
  r.m[2][2] = T(1) - T(2) * (x * x + y * y);
  return r;
}
// VJP of quat_to_rotmat: accumulates d/dq (unnormalised) into v_q.
template <typename T>
GSW_HD void quat_to_rotmat_vjp(const T q_in[4], const Mat3<T>& v_R, T v_q[4]) {
  const T norm = sqrt(q_in[0] * q_in[0] + q_in[1] * q_in[1] + q_in[2] * q_in[2] +
                      q_in[3] * q_in[3]);
  const T inv = T(1) / norm;
  const T w = q_in[0] * inv, x = q_in[1] * inv, y = q_in[2] * inv, z = q_in[3] * inv;
  const auto& g = v_R.m;
  // gradient w.r.t. the normalised quaternion
  T vn[4];
  vn[0] = T(2) * (-z * g[0][1] + y * g[0][2] + z * g[1][0] - x * g[1][2] - y * g[2][0] +
                  x * g[2][1]);
  vn[1] = T(2) * (y * g[0][1] + z * g[0][2] + y * g[1][0] - T(2) * x * g[1][1] - w * g[1][2] +
                  z * g[2][0] + w * g[2][1] - T(2) * x * g[2][2]);
  vn[2] = T(2) * (-T(2) * y * g[0][0] + x * g[0][1] + w * g[0][2] + x * g[1][0] + z * g[1][2] -
                  w * g[2][0] + z * g[2][1] - T(2) * y * g[2][2]);
  vn[3] = T(2) * (-T(2) * z * g[0][0] - w * g[0][1] + x * g[0][2] + w * g[1][0] -
                  T(2) * z * g[1][1] + y * g[1][2] + x * g[2][0] + y * g[2][1]);
  // through the normalisation n = q / |q|: v_q = (vn - n (n . vn)) / |q|
  const T n_dot = w * vn[0] + x * vn[1] + y * vn[2] + z * vn[3];
  v_q[0] += (vn[0] - w * n_dot) * inv;
  v_q[1] += (vn[1] - x * n_dot) * inv;
  v_q[2] += (vn[2] - y * n_dot) * inv;
  v_q[3] += (vn[3] - z * n_dot) * inv;
}

// Sigma = R S S^T R^T with S = diag(exp(log_scale)).
template <typename T>
GSW_HD Mat3<T> covariance_3d(const T quat[4], const T log_scale[3]) {
  const Mat3<T> R = quat_to_rotmat(quat);
  const T s[3] = {exp(log_scale[0]), exp(log_scale[1]), exp(log_scale[2])};
  Mat3<T> M;  // M = R S
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) M.m[i][j] = R.m[i][j] * s[j];
  return matmul_bt(M, M);
}
// VJP of covariance_3d for a symmetric cotangent v_cov; accumulates into v_quat, v_log_scale.
template <typename T>
GSW_HD void covariance_3d_vjp(const T quat[4], const T log_scale[3], const Mat3<T>& v_cov,
                              T v_quat[4], T v_log_scale[3]) {
  const Mat3<T> R = quat_to_rotmat(quat);
  const T s[3] = {exp(log_scale[0]), exp(log_scale[1]), exp(log_scale[2])};
  Mat3<T> M;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) M.m[i][j] = R.m[i][j] * s[j];
  // Sigma = M M^T  =>  v_M = (v_cov + v_cov^T) M = 2 v_cov M for symmetric v_cov.
  Mat3<T> v_M = matmul(v_cov, M);
  Mat3<T> v_R;
  for (int j = 0; j < 3; ++j) {
    T v_s = T(0);
    for (int i = 0; i < 3; ++i) {
      v_M.m[i][j] *= T(2);
      v_R.m[i][j] = v_M.m[i][j] * s[j];
      v_s += v_M.m[i][j] * R.m[i][j];
    }
    v_log_scale[j] += v_s * s[j];
  }
  quat_to_rotmat_vjp(quat, v_R, v_quat);
}

// ------------------------------------------------------------------ EWA projection

// Projection of a camera-space mean and covariance to the image (before dilation).
template <typename T>
struct Projection {
  Vec2<T> mean2d;
  Sym2<T> cov2d;
};

// Frustum limits of x/z (or y/z): the image extent plus a FRUSTUM_CLAMP margin. Equals
// +-FRUSTUM_CLAMP * tan(fov/2) for a centred principal point.
template <typename T>
GSW_HD void frustum_limits(T focal, T principal, int size, T& lim_neg, T& lim_pos) {
  const T tan_half = T(0.5) * T(size) / focal;
  const T margin = (T(FRUSTUM_CLAMP) - T(1)) * tan_half;
  lim_neg = principal / focal + margin;
  lim_pos = (T(size) - principal) / focal + margin;
}

// Clamped x/z and whether it was clamped.
template <typename T>
GSW_HD T clamp_ratio(T r, T lim_neg, T lim_pos, bool& clamped) {
  clamped = (r < -lim_neg) || (r > lim_pos);
  return r < -lim_neg ? -lim_neg : (r > lim_pos ? lim_pos : r);
}

// The EWA Jacobian of the perspective map at a camera-space mean p, with x/z and y/z clamped to
// the frustum limits: J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]]. Computed once per Gaussian and
// shared by project_ewa and its VJP.
template <typename T>
struct EwaJacobian {
  T iz, u, v;              // 1/z and the clamped ratios
  bool clamped_x, clamped_y;
  T j00, j02, j11, j12;    // the non-zero entries of J
};

template <typename T>
GSW_HD EwaJacobian<T> ewa_jacobian(const Camera<T>& cam, const Vec3<T>& p) {
  T lxn, lxp, lyn, lyp;
  frustum_limits(cam.fx, cam.cx, cam.width, lxn, lxp);
  frustum_limits(cam.fy, cam.cy, cam.height, lyn, lyp);
  EwaJacobian<T> J;
  J.iz = T(1) / p.z;
  J.u = clamp_ratio(p.x * J.iz, lxn, lxp, J.clamped_x);
  J.v = clamp_ratio(p.y * J.iz, lyn, lyp, J.clamped_y);
  J.j00 = cam.fx * J.iz;
  J.j02 = -cam.fx * J.u * J.iz;
  J.j11 = cam.fy * J.iz;
  J.j12 = -cam.fy * J.v * J.iz;
  return J;
}

// Image-space mean and J cov J^T of a camera-space mean p and covariance cov (J = ewa_jacobian).
template <typename T>
GSW_HD Projection<T> project_ewa(const Camera<T>& cam, const Vec3<T>& p, const Mat3<T>& cov,
                                 const EwaJacobian<T>& J) {
  const T iz = J.iz, j00 = J.j00, j02 = J.j02, j11 = J.j11, j12 = J.j12;
  // cov2d = J cov J^T
  const auto& c = cov.m;
  const T r0[3] = {j00 * c[0][0] + j02 * c[2][0], j00 * c[0][1] + j02 * c[2][1],
                   j00 * c[0][2] + j02 * c[2][2]};
  const T r1[3] = {j11 * c[1][0] + j12 * c[2][0], j11 * c[1][1] + j12 * c[2][1],
                   j11 * c[1][2] + j12 * c[2][2]};
  Projection<T> out;
  out.cov2d.a = r0[0] * j00 + r0[2] * j02;
  out.cov2d.b = r0[1] * j11 + r0[2] * j12;
  out.cov2d.c = r1[1] * j11 + r1[2] * j12;
  out.mean2d.x = cam.fx * p.x * iz + cam.cx;
  out.mean2d.y = cam.fy * p.y * iz + cam.cy;
  return out;
}
// VJP of project_ewa (same J): accumulates into v_p (camera-space mean) and v_cov (symmetric).
template <typename T>
GSW_HD void project_ewa_vjp(const Camera<T>& cam, const Vec3<T>& p, const Mat3<T>& cov,
                            const EwaJacobian<T>& Jac, const Vec2<T>& v_mean2d, const Sym2<T>& v_cov2d,
                            Vec3<T>& v_p, Mat3<T>& v_cov) {
  const T iz = Jac.iz, u = Jac.u, v = Jac.v;
  const bool clx = Jac.clamped_x, cly = Jac.clamped_y;
  const T J[2][3] = {{Jac.j00, T(0), Jac.j02}, {T(0), Jac.j11, Jac.j12}};
  // Full symmetric 2x2 cotangent G (off-diagonal carries half of v_b each).
  const T G[2][2] = {{v_cov2d.a, T(0.5) * v_cov2d.b}, {T(0.5) * v_cov2d.b, v_cov2d.c}};
  // v_cov += J^T G J
  T GJ[2][3];
  for (int i = 0; i < 2; ++i)
    for (int k = 0; k < 3; ++k) GJ[i][k] = G[i][0] * J[0][k] + G[i][1] * J[1][k];
  for (int k = 0; k < 3; ++k)
    for (int l = 0; l < 3; ++l) v_cov.m[k][l] += J[0][k] * GJ[0][l] + J[1][k] * GJ[1][l];
  // v_J = 2 G J cov
  T v_J[2][3];
  for (int i = 0; i < 2; ++i)
    for (int l = 0; l < 3; ++l)
      v_J[i][l] = T(2) * (GJ[i][0] * cov.m[0][l] + GJ[i][1] * cov.m[1][l] +
                          GJ[i][2] * cov.m[2][l]);
  // J00 = fx/z, J11 = fy/z, J02 = -fx u/z, J12 = -fy v/z with u = x/z unless clamped.
  const T iz2 = iz * iz;
  T v_z = -cam.fx * iz2 * v_J[0][0] - cam.fy * iz2 * v_J[1][1];
  v_z += cam.fx * u * iz2 * v_J[0][2] + cam.fy * v * iz2 * v_J[1][2];
  T v_u = -cam.fx * iz * v_J[0][2];
  T v_v = -cam.fy * iz * v_J[1][2];
  // mean2d = (fx x/z + cx, fy y/z + cy) uses the unclamped ratios.
  T v_x = cam.fx * iz * v_mean2d.x;
  T v_y = cam.fy * iz * v_mean2d.y;
  v_z -= (cam.fx * p.x * v_mean2d.x + cam.fy * p.y * v_mean2d.y) * iz2;
  if (!clx) {
    v_x += v_u * iz;
    v_z -= v_u * p.x * iz2;
  }
  if (!cly) {
    v_y += v_v * iz;
    v_z -= v_v * p.y * iz2;
  }
  v_p.x += v_x;
  v_p.y += v_y;
  v_p.z += v_z;
}

// ------------------------------------------------------------------ 2-D conic and footprint

// Dilated 2-D covariance and its inverse (the conic). Returns false when not invertible.
template <typename T>
GSW_HD bool conic_from_cov2d(const Sym2<T>& cov2d, Sym2<T>& conic, T& det) {
  const T a = cov2d.a + T(COV2D_DILATION), b = cov2d.b, c = cov2d.c + T(COV2D_DILATION);
  det = a * c - b * b;
  if (!(det > T(0))) return false;
  const T inv = T(1) / det;
  conic = {c * inv, -b * inv, a * inv};
  return true;
}
// VJP of conic_from_cov2d (v_conic in free-parameter convention); returns v_cov2d likewise.
template <typename T>
GSW_HD Sym2<T> conic_from_cov2d_vjp(const Sym2<T>& conic, const Sym2<T>& v_conic) {
  // Y = X^{-1}: dL/dX = -Y G Y with G the full symmetric cotangent of Y.
  const T g00 = v_conic.a, g01 = T(0.5) * v_conic.b, g11 = v_conic.c;
  const T y00 = conic.a, y01 = conic.b, y11 = conic.c;
  // H = G Y
  const T h00 = g00 * y00 + g01 * y01, h01 = g00 * y01 + g01 * y11;
  const T h10 = g01 * y00 + g11 * y01, h11 = g01 * y01 + g11 * y11;
  const T r00 = -(y00 * h00 + y01 * h10);
  const T r01 = -(y00 * h01 + y01 * h11);
  const T r11 = -(y01 * h01 + y11 * h11);
  return {r00, T(2) * r01, r11};
}

// Exponent below which a splat of this opacity is certainly skipped (alpha < ALPHA_MIN); the
// caller tests `power < skip_power` before paying for exp(). -inf-safe for opacity 0.
template <typename T>
GSW_HD T splat_skip_power(T opacity) {
  return log(T(ALPHA_MIN) / opacity) - T(SKIP_LOG_MARGIN);
}

// Extent, in standard deviations, of the ellipse {power >= splat_skip_power(opacity)} outside
// which a splat of this opacity is certainly skipped: sqrt(-2 skip_power), about
// sqrt(2 ln(opacity / ALPHA_MIN)). 0 when it is skipped everywhere (opacity below ALPHA_MIN, NaN).
template <typename T>
GSW_HD T alpha_extent_sigmas(T opacity) {
  const T skip = splat_skip_power(opacity);
  return skip < T(0) ? sqrt(T(-2) * skip) : T(0);
}

// Pixel radius of the footprint (opacity-aware): INRIA's ceil(RADIUS_SIGMAS sqrt(l1)), l1 the
// largest eigenvalue of the dilated covariance, or, when smaller, ceil(e sqrt(l1)) + 1 with
// e = alpha_extent_sigmas(opacity): a faint splat reaches ALPHA_MIN only within e < RADIUS_SIGMAS
// sigmas. The + 1 pixel covers tile_rect (INRIA's getRect), which can leave out the last pixel
// of a radius on the right and bottom, so the tighter radius changes no rendered pixel; it only
// drops (tile, splat) pairs that would be skipped. 0 when the splat can never reach ALPHA_MIN.
template <typename T>
GSW_HD int footprint_radius(const Sym2<T>& cov2d, T det, T opacity) {
  const T extent = alpha_extent_sigmas(opacity);
  if (!(extent > T(0))) return 0;
  const T a = cov2d.a + T(COV2D_DILATION), c = cov2d.c + T(COV2D_DILATION);
  const T mid = T(0.5) * (a + c);
  const T disc = mid * mid - det;
  const T sigma = sqrt(mid + sqrt(disc > T(EIGEN_FLOOR) ? disc : T(EIGEN_FLOOR)));
  const T r_max = ceil(T(RADIUS_SIGMAS) * sigma);
  const T r_alpha = ceil(extent * sigma) + T(1);
  const T r = r_alpha < r_max ? r_alpha : r_max;
  return r < T(MAX_RADIUS) ? static_cast<int>(r) : MAX_RADIUS;  // also maps NaN to MAX_RADIUS
}

// Tile rectangle [x0, x1) x [y0, y1) touched by a footprint (INRIA getRect, in pixel-centre
// coordinates mean2d - 0.5). Returns the number of tiles.
template <typename T>
GSW_HD int tile_rect(const Vec2<T>& mean2d, int radius, int tiles_x, int tiles_y, int& x0,
                     int& y0, int& x1, int& y1) {
  const T px = mean2d.x - T(0.5), py = mean2d.y - T(0.5);
  const T ts = T(TILE_SIZE);
  auto clampi = [](T v, int hi) -> int {
    const T f = floor(v);
    return !(f >= T(0)) ? 0 : (f > T(hi) ? hi : static_cast<int>(f));  // NaN -> 0
  };
  x0 = clampi((px - T(radius)) / ts, tiles_x);
  x1 = clampi((px + T(radius) + ts - T(1)) / ts, tiles_x);
  y0 = clampi((py - T(radius)) / ts, tiles_y);
  y1 = clampi((py + T(radius) + ts - T(1)) / ts, tiles_y);
  return (x1 - x0) * (y1 - y0);
}

// ------------------------------------------------------------------ spherical harmonics

// Number of SH coefficients for a degree.
GSW_HD int sh_num_coeffs(int degree) { return (degree + 1) * (degree + 1); }

// Real SH basis of degree `degree` at the unit direction (x, y, z); fills basis[0..(d+1)^2).
template <typename T>
GSW_HD void sh_basis(int degree, T x, T y, T z, T* basis) {
  basis[0] = T(SH_C0);
  if (degree < 1) return;
  basis[1] = -T(SH_C1) * y;
  basis[2] = T(SH_C1) * z;
  basis[3] = -T(SH_C1) * x;
  if (degree < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  basis[4] = T(SH_C2_0) * xy;
  basis[5] = T(SH_C2_1) * yz;
  basis[6] = T(SH_C2_2) * (T(2) * zz - xx - yy);
  basis[7] = T(SH_C2_3) * xz;
  basis[8] = T(SH_C2_4) * (xx - yy);
  if (degree < 3) return;
  basis[9] = T(SH_C3_0) * y * (T(3) * xx - yy);
  basis[10] = T(SH_C3_1) * xy * z;
  basis[11] = T(SH_C3_2) * y * (T(4) * zz - xx - yy);
  basis[12] = T(SH_C3_3) * z * (T(2) * zz - T(3) * xx - T(3) * yy);
  basis[13] = T(SH_C3_4) * x * (T(4) * zz - xx - yy);
  basis[14] = T(SH_C3_5) * z * (xx - yy);
  basis[15] = T(SH_C3_6) * x * (xx - T(3) * yy);
}
// VJP of sh_basis w.r.t. the unit direction, for cotangents v_basis.
template <typename T>
GSW_HD Vec3<T> sh_basis_vjp(int degree, T x, T y, T z, const T* v_basis) {
  Vec3<T> g = {T(0), T(0), T(0)};
  if (degree < 1) return g;
  g.y -= T(SH_C1) * v_basis[1];
  g.z += T(SH_C1) * v_basis[2];
  g.x -= T(SH_C1) * v_basis[3];
  if (degree < 2) return g;
  const T xx = x * x, yy = y * y, zz = z * z;
  g.x += T(SH_C2_0) * y * v_basis[4];
  g.y += T(SH_C2_0) * x * v_basis[4];
  g.y += T(SH_C2_1) * z * v_basis[5];
  g.z += T(SH_C2_1) * y * v_basis[5];
  g.x += T(SH_C2_2) * (-T(2) * x) * v_basis[6];
  g.y += T(SH_C2_2) * (-T(2) * y) * v_basis[6];
  g.z += T(SH_C2_2) * (T(4) * z) * v_basis[6];
  g.x += T(SH_C2_3) * z * v_basis[7];
  g.z += T(SH_C2_3) * x * v_basis[7];
  g.x += T(SH_C2_4) * (T(2) * x) * v_basis[8];
  g.y += T(SH_C2_4) * (-T(2) * y) * v_basis[8];
  if (degree < 3) return g;
  // 9: y (3xx - yy)
  g.x += T(SH_C3_0) * (T(6) * x * y) * v_basis[9];
  g.y += T(SH_C3_0) * (T(3) * xx - T(3) * yy) * v_basis[9];
  // 10: x y z
  g.x += T(SH_C3_1) * y * z * v_basis[10];
  g.y += T(SH_C3_1) * x * z * v_basis[10];
  g.z += T(SH_C3_1) * x * y * v_basis[10];
  // 11: y (4zz - xx - yy)
  g.x += T(SH_C3_2) * (-T(2) * x * y) * v_basis[11];
  g.y += T(SH_C3_2) * (T(4) * zz - xx - T(3) * yy) * v_basis[11];
  g.z += T(SH_C3_2) * (T(8) * y * z) * v_basis[11];
  // 12: z (2zz - 3xx - 3yy)
  g.x += T(SH_C3_3) * (-T(6) * x * z) * v_basis[12];
  g.y += T(SH_C3_3) * (-T(6) * y * z) * v_basis[12];
  g.z += T(SH_C3_3) * (T(6) * zz - T(3) * xx - T(3) * yy) * v_basis[12];
  // 13: x (4zz - xx - yy)
  g.x += T(SH_C3_4) * (T(4) * zz - T(3) * xx - yy) * v_basis[13];
  g.y += T(SH_C3_4) * (-T(2) * x * y) * v_basis[13];
  g.z += T(SH_C3_4) * (T(8) * x * z) * v_basis[13];
  // 14: z (xx - yy)
  g.x += T(SH_C3_5) * (T(2) * x * z) * v_basis[14];
  g.y += T(SH_C3_5) * (-T(2) * y * z) * v_basis[14];
  g.z += T(SH_C3_5) * (xx - yy) * v_basis[14];
  // 15: x (xx - 3yy)
  g.x += T(SH_C3_6) * (T(3) * xx - T(3) * yy) * v_basis[15];
  g.y += T(SH_C3_6) * (-T(6) * x * y) * v_basis[15];
  return g;
}

// Unit vector and its VJP.
template <typename T>
GSW_HD Vec3<T> normalize3(const Vec3<T>& v) {
  const T inv = T(1) / sqrt(v.x * v.x + v.y * v.y + v.z * v.z);
  return {v.x * inv, v.y * inv, v.z * inv};
}
template <typename T>
GSW_HD Vec3<T> normalize3_vjp(const Vec3<T>& v, const Vec3<T>& v_n) {
  const T inv = T(1) / sqrt(v.x * v.x + v.y * v.y + v.z * v.z);
  const Vec3<T> n = {v.x * inv, v.y * inv, v.z * inv};
  const T d = n.x * v_n.x + n.y * v_n.y + n.z * v_n.z;
  return {(v_n.x - n.x * d) * inv, (v_n.y - n.y * d) * inv, (v_n.z - n.z * d) * inv};
}

// The unclamped colour sum_k basis_k sh[k] + SH_COLOR_OFFSET (one order for forward and VJP).
template <typename T>
GSW_HD void sh_color_sum(int K, const T* basis, const T* sh, T* rgb) {
  rgb[0] = rgb[1] = rgb[2] = T(SH_COLOR_OFFSET);
  for (int k = 0; k < K; ++k)
    for (int ch = 0; ch < 3; ++ch) rgb[ch] += basis[k] * sh[3 * k + ch];
}
// View-dependent colour: rgb = max(0, sum_k basis_k(dir) sh[k] + SH_COLOR_OFFSET), with
// dir = normalise(mean - camera centre). `sh` points to K x 3 coefficients (channel fastest).
template <typename T>
GSW_HD Vec3<T> sh_to_color(int degree, const Vec3<T>& dir_unnorm, const T* sh) {
  const Vec3<T> d = normalize3(dir_unnorm);
  T basis[16];
  sh_basis(degree, d.x, d.y, d.z, basis);
  T rgb[3];
  sh_color_sum(sh_num_coeffs(degree), basis, sh, rgb);
  return {rgb[0] > T(0) ? rgb[0] : T(0), rgb[1] > T(0) ? rgb[1] : T(0),
          rgb[2] > T(0) ? rgb[2] : T(0)};
}
// VJP of sh_to_color (a clamped channel has zero gradient: the colour is recomputed here, so the
// forward's colours need not be kept for the backward). Accumulates into v_sh (K x 3) and returns
// the cotangent of the unnormalised direction.
template <typename T>
GSW_HD Vec3<T> sh_to_color_vjp(int degree, const Vec3<T>& dir_unnorm, const T* sh,
                               const Vec3<T>& v_color, T* v_sh) {
  const Vec3<T> d = normalize3(dir_unnorm);
  T basis[16];
  sh_basis(degree, d.x, d.y, d.z, basis);
  const int K = sh_num_coeffs(degree);
  T rgb[3];
  sh_color_sum(K, basis, sh, rgb);
  const T vc[3] = {rgb[0] > T(0) ? v_color.x : T(0), rgb[1] > T(0) ? v_color.y : T(0),
                   rgb[2] > T(0) ? v_color.z : T(0)};
  T v_basis[16];
  for (int k = 0; k < K; ++k) {
    v_basis[k] = T(0);
    for (int ch = 0; ch < 3; ++ch) {
      v_sh[3 * k + ch] += basis[k] * vc[ch];
      v_basis[k] += sh[3 * k + ch] * vc[ch];
    }
  }
  const Vec3<T> v_d = sh_basis_vjp(degree, d.x, d.y, d.z, v_basis);
  return normalize3_vjp(dir_unnorm, v_d);
}

// ------------------------------------------------------------------ per-pixel blending

// Exponent of the 2-D Gaussian at pixel centre (px, py): -0.5 d^T conic d, d = mean2d - p.
// On the device its roundings are fixed by two explicit FMAs (the scalings by -0.5 and -1 are
// exact), so every CUDA blend kernel gets the same bits whatever the compiler would fuse: kernels
// with several pixels per thread share the pixels' common terms, which changes the contraction
// the compiler picks, and the backward must blend exactly the splats the forward blended.
template <typename T>
GSW_HD T gaussian_power(const Sym2<T>& conic, T mean_x, T mean_y, T px, T py) {
  const T dx = mean_x - px, dy = mean_y - py;
#if defined(__CUDA_ARCH__)
  return fma(dy, fma(T(-0.5) * conic.c, dy, -conic.b * dx), T(-0.5) * conic.a * dx * dx);
#else
  return Scalar<T>(-0.5) * (conic.a * dx * dx + conic.c * dy * dy) - conic.b * dx * dy;
#endif
}

// Bit reinterpretation float <-> int32 of host_blend_exp (specialised for the CPU backend's lane
// vectors in cpu/simd.h).
template <typename F>
struct FloatBits;
template <>
struct FloatBits<float> {
  using I = int32_t;
  static I to_bits(float f) {
    I i;
    __builtin_memcpy(&i, &f, sizeof(float));
    return i;
  }
  static float from_bits(I i) {
    float f;
    __builtin_memcpy(&f, &i, sizeof(float));
    return f;
  }
};

// exp() of the blending hot loop. Host float32: a branch-free Cephes-style approximation
// (relative error ~2 ulp for arguments in [-87, 0]) for a float or a lane vector of floats:
// n = round(x log2 e) by the 1.5 * 2^23 shift, exp(r) of the remainder by Cephes' polynomial in
// Estrin's form (short dependency chains: pixel loops are latency-bound), times 2^n. Host float64
// and all device code use the library exp. (Separate host overloads, so every translation unit
// sees the same definition of blend_exp.)
template <typename F>
inline F host_blend_exp_f32(F x) {
  using B = FloatBits<F>;
  x = x < -87.0f ? -87.0f : x;  // clamp to [-87, 0] (NaN passes through)
  x = x > 0.0f ? 0.0f : x;
  const F t = x * 1.44269504088896341f + 12582912.0f;  // 1.5 * 2^23 + n: n in t's low bits
  const F nf = t - 12582912.0f;
  const F r = (x - nf * 0.693359375f) + nf * 2.12194440e-4f;
  const F r2 = r * r;
  const F p = ((1.9875691500e-4f * r + 1.3981999507e-3f) * r2 + (8.3334519073e-3f * r + 4.1665795894e-2f)) * r2 +
              (1.6666665459e-1f * r + 5.0000001201e-1f);
  const F y = p * r2 + (r + 1.0f);
  return y * B::from_bits((B::to_bits(t) + 127) << 23);  // 2^n (t's bits are 0x4B400000 + n)
}
inline float host_blend_exp(float x) { return host_blend_exp_f32(x); }
inline double host_blend_exp(double x) { return exp(x); }
// Host blend_exp of T (specialised for the CPU backend's lane vectors in cpu/simd.h).
template <typename T>
struct HostBlendExp {
  static T apply(T x) { return host_blend_exp(x); }
};

template <typename T>
GSW_HD T blend_exp(T x) {
#if defined(__CUDA_ARCH__)
  return exp(x);
#else
  return HostBlendExp<T>::apply(x);
#endif
}

// Blending opacity of one splat at one pixel; returns 0 when the splat is skipped
// (power > 0 or alpha < ALPHA_MIN). Branch-free so pixel loops vectorize. splat_gaussian is its
// Gaussian factor exp(min(power, 0)).
template <typename T>
GSW_HD T splat_gaussian(T power) {
  return blend_exp(power > Scalar<T>(0) ? Scalar<T>(0) : power);
}
// splat_alpha for a precomputed G = splat_gaussian(power) (backward passes reuse G in
// splat_alpha_vjp_from_gaussian instead of evaluating exp() twice).
template <typename T>
GSW_HD T splat_alpha_from_gaussian(T opacity, T power, T G) {
  using S = Scalar<T>;
  const T a = opacity * G;
  const T alpha = a < S(ALPHA_MAX) ? a : S(ALPHA_MAX);
  const T kept = alpha < S(ALPHA_MIN) ? S(0) : alpha;
  return power > S(0) ? S(0) : kept;
}
template <typename T>
GSW_HD T splat_alpha(T opacity, T power) {
  return splat_alpha_from_gaussian(opacity, power, splat_gaussian(power));
}

// Half extents (pixels) of the axis-aligned box around the 2-D mean outside which a splat is
// certainly skipped: the ellipse {power >= skip_power}. Returns false if the splat is skipped
// everywhere (skip_power >= 0, i.e. opacity below ALPHA_MIN).
template <typename T>
GSW_HD bool splat_extent(const Sym2<T>& conic, T skip_power, T& ex, T& ey) {
  if (!(skip_power < T(0))) return false;
  const T det = conic.a * conic.c - conic.b * conic.b;
  const T r2 = T(-2) * skip_power;
  ex = sqrt(r2 * conic.c / det);
  ey = sqrt(r2 * conic.a / det);
  return true;
}

// Indices [out_lo, out_hi) - lo of the pixels lo .. hi - 1 whose centres (i + 0.5) lie in [c - e, c + e]
// (a tile-local range; NaN c or e: empty).
template <typename T>
GSW_HD void pixel_span(T c, T e, int lo, int hi, int& out_lo, int& out_hi) {
  const T l = ceil(c - e - T(0.5)), h = floor(c + e - T(0.5)) + T(1);
  const T lc = l < T(hi) ? l : T(hi), hc = h < T(hi) ? h : T(hi);
  out_lo = static_cast<int>(T(lo) < lc ? lc : T(lo)) - lo;
  out_hi = static_cast<int>(T(lo) < hc ? hc : T(lo)) - lo;
}

// Rows of the tile whose first pixel row is y0 in which a splat can be blended, as a bit mask (bit r:
// row y0 + r): the rows whose pixel centres lie within the y extent of its skip ellipse (splat_extent)
// widened by `margin` pixels. 0 when it is skipped everywhere; every row when its extent or centre is
// not a number. A conservative cull: the rows left out are those where splat_alpha is 0.
template <typename T>
GSW_HD uint32_t splat_row_mask(const Sym2<T>& conic, T opacity, T my, int y0, T margin) {
  constexpr uint32_t kAll = (uint32_t(1) << TILE_SIZE) - 1u;
  T ex, ey;
  if (!splat_extent(conic, splat_skip_power(opacity), ex, ey)) return opacity == opacity ? 0u : kAll;
  if (!(ey >= T(0)) || !(my == my)) return kAll;
  int lo, hi;
  pixel_span(my, ey + margin, y0, y0 + TILE_SIZE, lo, hi);
  return ((uint32_t(1) << hi) - 1u) & ~((uint32_t(1) << lo) - 1u);
}

// Cotangents of one splat's per-pixel alpha w.r.t. its 2-D parameters.
template <typename T>
struct SplatGrad {
  Vec2<T> mean2d;
  Sym2<T> conic;
  T opacity;
};

// VJP of splat_alpha at one pixel for a non-skipped splat, given the offset (dx, dy) = mean2d -
// pixel centre and the Gaussian factor G = exp(exponent) at that pixel: returns the cotangent
// contributions (zero where alpha is clamped to ALPHA_MAX). Branch-free.
template <typename T>
GSW_HD SplatGrad<T> splat_alpha_vjp_from_gaussian(const Sym2<T>& conic, T dx, T dy, T G, T opacity,
                                                  T v_alpha) {
  using S = Scalar<T>;
  const T v = opacity * G < S(ALPHA_MAX) ? v_alpha : S(0);
  const T v_power = opacity * G * v;
  SplatGrad<T> g;
  g.opacity = G * v;
  g.conic.a = S(-0.5) * dx * dx * v_power;
  g.conic.b = -dx * dy * v_power;
  g.conic.c = S(-0.5) * dy * dy * v_power;
  g.mean2d.x = -(conic.a * dx + conic.b * dy) * v_power;
  g.mean2d.y = -(conic.b * dx + conic.c * dy) * v_power;
  return g;
}

// Whether a pixel with transmittance T stops before blending a splat of opacity alpha
// (INRIA: that splat is not blended). A lane mask for lane vectors.
template <typename T>
GSW_HD auto blend_terminates(T transmittance, T alpha) {
  return transmittance * (Scalar<T>(1) - alpha) < Scalar<T>(T_MIN);
}

// ------------------------------------------------------------------ per-pixel blend backward

// Cotangents of one pixel's outputs, fixed during its back-to-front walk.
template <typename T>
struct PixelCotangents {
  T color[3];   // v_image
  T depth;      // v_depth
  T t_final;    // the pixel's final transmittance T_final
  T v_t_final;  // d(loss)/d(T_final): background and the alpha output (alpha = 1 - T_final)
};

// State of one pixel's back-to-front walk over the splats it blended.
template <typename T>
struct BlendBackwardPixel {
  T tr;         // transmittance behind the current splat (starts at T_final)
  T behind[4];  // colour and depth behind the current splat, per unit transmittance
};

// One splat at one pixel: conic, offset (dx, dy) = mean2d - pixel centre, Gaussian factor
// G = splat_gaussian(power), opacity and the forward's alpha there (0: not blended); colour and
// depth are the splat's (Scalar<T>: the same for every lane).
template <typename T>
struct SplatAtPixel {
  Sym2<T> conic;
  T dx, dy, G, opacity, alpha;
  Scalar<T> color[3], depth;
};

// Cotangents of one splat from one pixel: through alpha (mean2d, conic, opacity), then colour
// and depth.
template <typename T>
struct BlendGrad {
  SplatGrad<T> splat;
  T color[3], depth;
};

// Adds one pixel's cotangents of a splat to its record sums acc[kBlendGrads] (core/constants.h). kDepth = false
// leaves acc[9] (depth) untouched.
template <bool kDepth = true, typename T>
GSW_HD void add_blend_grad(const BlendGrad<T>& g, T* acc) {
  acc[0] = acc[0] + g.splat.mean2d.x;
  acc[1] = acc[1] + g.splat.mean2d.y;
  acc[2] = acc[2] + g.splat.conic.a;
  acc[3] = acc[3] + g.splat.conic.b;
  acc[4] = acc[4] + g.splat.conic.c;
  acc[5] = acc[5] + g.splat.opacity;
  for (int c = 0; c < 3; ++c) acc[6 + c] = acc[6 + c] + g.color[c];
  if constexpr (kDepth) acc[9] = acc[9] + g.depth;
}

// One step of a pixel's back-to-front blend backward: undoes splat s (T_i = T_{i+1} / (1 - alpha)),
// returns its cotangents from this pixel and moves the colour/depth behind it past s. Where
// alpha = 0 the state is unchanged and every cotangent is 0. kDepth / kFinalT = false leave out the
// depth and T_final terms (identical results where v.depth / v.v_t_final are 0; v.depth /
// v.t_final / v.v_t_final and px.behind[3] are then not read, and the returned depth is 0).
template <bool kDepth = true, bool kFinalT = true, typename T>
GSW_HD BlendGrad<T> blend_backward_step(const SplatAtPixel<T>& s, const PixelCotangents<T>& v,
                                        BlendBackwardPixel<T>& px) {
  using S = Scalar<T>;
  const T om = S(1) - s.alpha;
  const T inv_om = S(1) / om;
  const T t = px.tr * inv_om;  // transmittance in front of s
  px.tr = t;
  const T w = s.alpha * t;
  BlendGrad<T> g;
  T v_alpha = (s.color[0] - px.behind[0]) * v.color[0] + (s.color[1] - px.behind[1]) * v.color[1] +
              (s.color[2] - px.behind[2]) * v.color[2];
  if constexpr (kDepth) v_alpha = v_alpha + (s.depth - px.behind[3]) * v.depth;
  v_alpha = t * v_alpha;
  if constexpr (kFinalT) v_alpha = v_alpha - v.t_final * inv_om * v.v_t_final;
  g.splat = splat_alpha_vjp_from_gaussian(s.conic, s.dx, s.dy, s.G, s.opacity,
                                          s.alpha > S(0) ? v_alpha : S(0));
  for (int c = 0; c < 3; ++c) {
    g.color[c] = w * v.color[c];
    px.behind[c] = s.alpha * s.color[c] + om * px.behind[c];
  }
  if constexpr (kDepth) {
    g.depth = w * v.depth;
    px.behind[3] = s.alpha * s.depth + om * px.behind[3];
  } else {
    g.depth = T{};
  }
  return g;
}


}  // namespace gsw
