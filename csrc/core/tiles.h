// Tile assignment of a splat (which 16x16 tiles it is binned to), shared unchanged by the CPU and
// CUDA binning and mirrored operation by operation in gsw/render/_reference (reference_tile_spans).
//
// A splat is binned to the tiles of its radius rectangle (tile_rect) that hold a pixel centre
// inside its skip ellipse {d : d^T conic d <= R2}, d = pixel centre - mean2d, where
//   R2 = (-2 splat_skip_power(opacity) + tol) (1 + 16 eps),
//   tol = 8 eps (|a| + |c| + 2 |b|) (radius + 2 TILE_SIZE)^2
// (eps the machine epsilon of T): tol bounds the rounding of the blend kernels' exponent over the
// rectangle, so every pixel whose alpha (as the kernels compute it) reaches ALPHA_MIN keeps the
// splat (SKIP_LOG_MARGIN covers exp() and the opacity). The ellipse uses a lower bound of the
// conic's determinant (it cancels for thin splats), and every coordinate a margin of
// BIN_MARGIN + 8 eps (|mean2d| + extents) pixels. Tile rows are cut to the ellipse's y extent;
// each row to the x span of the ellipse over the row's band of pixel-centre heights (the chords at
// the band's two ends, or the ellipse's leftmost / rightmost point when it lies in the band).
// Splats that are faint everywhere (skip power >= 0) get no tile; degenerate or non-finite
// conics fall back to the whole rectangle.
//
// All arithmetic goes through the rn_* helpers: one IEEE rounding per operation on every backend
// (no FMA contraction, no fast-math division / square root on CUDA), so the counting and filling
// passes of every backend take the same decisions bit for bit.
#pragma once

#include "math.h"

namespace gsw {

#if defined(__CUDA_ARCH__)
GSW_HD float rn_add(float a, float b) { return __fadd_rn(a, b); }
GSW_HD float rn_sub(float a, float b) { return __fsub_rn(a, b); }
GSW_HD float rn_mul(float a, float b) { return __fmul_rn(a, b); }
GSW_HD float rn_div(float a, float b) { return __fdiv_rn(a, b); }
GSW_HD float rn_sqrt(float a) { return __fsqrt_rn(a); }
GSW_HD double rn_add(double a, double b) { return __dadd_rn(a, b); }
GSW_HD double rn_sub(double a, double b) { return __dsub_rn(a, b); }
GSW_HD double rn_mul(double a, double b) { return __dmul_rn(a, b); }
GSW_HD double rn_div(double a, double b) { return __ddiv_rn(a, b); }
GSW_HD double rn_sqrt(double a) { return __dsqrt_rn(a); }
#else
template <typename T>
GSW_HD T rn_add(T a, T b) { return a + b; }
template <typename T>
GSW_HD T rn_sub(T a, T b) { return a - b; }
template <typename T>
GSW_HD T rn_mul(T a, T b) { return a * b; }
template <typename T>
GSW_HD T rn_div(T a, T b) { return a / b; }
template <typename T>
GSW_HD T rn_sqrt(T a) { return sqrt(a); }
#endif

// Machine epsilon of the argument's type.
GSW_HD float machine_eps(float) { return 1.1920928955078125e-07f; }
GSW_HD double machine_eps(double) { return 2.220446049250313e-16; }

template <typename T>
GSW_HD T abs_value(T x) {
  return x < T(0) ? -x : x;
}

// Tiles a splat is binned to: rows [y0, y1), each row the columns of footprint_row.
template <typename T>
struct TileFootprint {
  int x0, y0, x1, y1;  // tile rectangle [x0, x1) x [y0, y1); empty: no tile
  bool ellipse;        // rows cut to the ellipse (else every row spans [x0, x1))
  T mx, my;            // centre (pixels)
  T inv_a, b;          // 1 / a and b of the conic
  T r2a, det;          // a R2 and the determinant's lower bound: chord half-width sqrt(r2a - det v^2) / a
  T ex, ey;            // half extents of the ellipse's bounding box
  T vstar;             // row offset v (pixel-centre height - my) of the leftmost point (rightmost: -vstar)
  T slack;             // tolerance of the test "vstar lies in the band"
  T margin;            // pixel margin of every coordinate
};

// Tile range [t_lo, t_hi) of the pixel centres (index + 0.5) in [lo, hi], clamped to [t0, t1)
// (NaN-safe: the whole range).
template <typename T>
GSW_HD void centre_tile_span(T lo, T hi, int t0, int t1, int& t_lo, int& t_hi) {
  const T inv_ts = T(1.0 / TILE_SIZE);
  const T fa = floor(rn_mul(ceil(rn_sub(lo, T(0.5))), inv_ts));
  const T fb = floor(rn_mul(floor(rn_sub(hi, T(0.5))), inv_ts)) + T(1);
  t_lo = fa > T(t0) ? (fa < T(t1) ? static_cast<int>(fa) : t1) : t0;
  t_hi = fb < T(t1) ? (fb > T(t_lo) ? static_cast<int>(fb) : t_lo) : t1;
}

// The tile footprint of a splat of the given radius (radius <= 0: none), see the file comment.
template <typename T>
GSW_HD TileFootprint<T> tile_footprint(const Vec2<T>& mean2d, const Sym2<T>& conic, T opacity,
                                       int radius, int tiles_x, int tiles_y) {
  TileFootprint<T> f;
  f.ellipse = false;
  f.x0 = f.y0 = f.x1 = f.y1 = 0;
  const T skip = splat_skip_power(opacity);
  if (radius <= 0 || tile_rect(mean2d, radius, tiles_x, tiles_y, f.x0, f.y0, f.x1, f.y1) == 0 ||
      skip >= T(0)) {
    f.x0 = f.y0 = f.x1 = f.y1 = 0;
    return f;
  }
  const T eps = machine_eps(T(0));
  const T a = conic.a, b = conic.b, c = conic.c;
  const T ac = rn_mul(a, c), bb = rn_mul(b, b);
  const T det = rn_sub(rn_sub(ac, bb), rn_mul(T(4) * eps, rn_add(ac, bb)));
  const T reach = T(radius) + T(2 * TILE_SIZE);
  const T spread = rn_add(rn_add(abs_value(a), abs_value(c)), T(2) * abs_value(b));
  const T tol = rn_mul(rn_mul(T(8) * eps, spread), rn_mul(reach, reach));
  const T r2 = rn_mul(rn_add(T(-2) * skip, tol), T(1) + T(16) * eps);
  if (!(a > T(0)) || !(c > T(0)) || !(det > T(0))) return f;  // the whole rectangle
  const T r2_det = rn_div(r2, det);
  const T ex = rn_sqrt(rn_mul(r2_det, c));
  const T ey = rn_sqrt(rn_mul(r2_det, a));
  if (!(ex <= T(MAX_RADIUS)) || !(ey <= T(MAX_RADIUS))) return f;
  const T mx = mean2d.x, my = mean2d.y;
  const T extent = rn_add(rn_add(abs_value(mx), abs_value(my)), rn_add(ex, ey));
  f.margin = rn_add(T(BIN_MARGIN), rn_mul(T(8) * eps, extent));
  int lo, hi;
  centre_tile_span(rn_sub(rn_sub(my, ey), f.margin), rn_add(rn_add(my, ey), f.margin), f.y0, f.y1, lo, hi);
  f.y0 = lo;
  f.y1 = hi;
  centre_tile_span(rn_sub(rn_sub(mx, ex), f.margin), rn_add(rn_add(mx, ex), f.margin), f.x0, f.x1, lo, hi);
  f.x0 = lo;
  f.x1 = hi;
  if (f.x0 >= f.x1 || f.y0 >= f.y1) {
    f.x0 = f.y0 = f.x1 = f.y1 = 0;
    return f;
  }
  f.ellipse = true;
  f.mx = mx;
  f.my = my;
  f.inv_a = rn_div(T(1), a);
  f.b = b;
  f.r2a = rn_mul(a, r2);
  f.det = det;
  f.ex = ex;
  f.ey = ey;
  f.vstar = rn_div(rn_mul(b, ex), c);
  f.slack = rn_mul(T(1e-3), rn_add(ey, T(1)));
  return f;
}

// Chord of the footprint's ellipse at row offset v (pixel-centre height - my): [lo, hi] in x.
template <typename T>
GSW_HD void footprint_chord(const TileFootprint<T>& f, T v, T& lo, T& hi) {
  const T disc = rn_sub(f.r2a, rn_mul(f.det, rn_mul(v, v)));
  const T s = rn_sqrt(disc > T(0) ? disc : T(0));
  const T bv = rn_mul(f.b, v);
  lo = rn_sub(f.mx, rn_mul(rn_add(bv, s), f.inv_a));
  hi = rn_sub(f.mx, rn_mul(rn_sub(bv, s), f.inv_a));
}

// Tile columns [xa, xb) of tile row ty (within [f.y0, f.y1)) that the splat is binned to.
template <typename T>
GSW_HD void footprint_row(const TileFootprint<T>& f, int ty, int& xa, int& xb) {
  xa = f.x0;
  xb = f.x1;
  if (!f.ellipse) return;
  const T top = T(ty * TILE_SIZE) + T(0.5), bottom = T(ty * TILE_SIZE) + T(TILE_SIZE - 0.5);
  const T d_top = rn_sub(top, f.my), d_bottom = rn_sub(bottom, f.my);
  const T ney = -f.ey;
  // A band holding the whole ellipse spans [mx - ex, mx + ex] (|vstar| <= ey): the rectangle's
  // columns, which the steps below would find too.
  if (d_top <= ney && d_bottom >= f.ey) return;
  const T vlo = d_top < ney ? ney : (d_top > f.ey ? f.ey : d_top);
  const T vhi = d_bottom < ney ? ney : (d_bottom > f.ey ? f.ey : d_bottom);
  T l0, h0, l1, h1;
  footprint_chord(f, vlo, l0, h0);
  footprint_chord(f, vhi, l1, h1);
  T lo = l0 < l1 ? l0 : l1, hi = h0 > h1 ? h0 : h1;
  const T band_lo = rn_sub(vlo, f.slack), band_hi = rn_add(vhi, f.slack);
  if (f.vstar >= band_lo && f.vstar <= band_hi) lo = rn_sub(f.mx, f.ex);
  if (-f.vstar >= band_lo && -f.vstar <= band_hi) hi = rn_add(f.mx, f.ex);
  centre_tile_span(rn_sub(lo, f.margin), rn_add(hi, f.margin), f.x0, f.x1, xa, xb);
}

// Number of tiles of a footprint.
template <typename T>
GSW_HD int footprint_tiles(const TileFootprint<T>& f) {
  int n = 0;
  for (int ty = f.y0; ty < f.y1; ++ty) {
    int xa, xb;
    footprint_row(f, ty, xa, xb);
    n += xb - xa;
  }
  return n;
}

}  // namespace gsw
