// CPU blending stage: forward, backward and per-Gaussian contribution, one tile per task.
//
// Each tile gathers its depth-ordered splats into a small packed array, then walks its pixels.
// Per-splat results of a tile are written to that tile's own range of the intersection list
// (scratch[slot]), and reduced per Gaussian afterwards in a fixed order: deterministic, no
// atomics, independent of the thread count.
#include <algorithm>
#include <memory>
#include <vector>

#include "cpu/backend_cpu.h"
#include "cpu/parallel.h"

namespace gsw::cpu {

namespace {

constexpr int kTilePixels = TILE_SIZE * TILE_SIZE;

template <typename T>
struct PackedSplat {
  Sym2<T> conic;
  T mx, my;
  T opacity;
  T skip_power;  // exponent below which alpha < ALPHA_MIN for sure
  // Skip ellipse d^T conic d <= r2 (r2 = -2 skip_power) per row: a conic.a r2, det(conic),
  // 1 / conic.a and conic.b / conic.a (see row_spans).
  T a_r2, det, inv_a, b_over_a;
  T ex, ey;  // half extents (pixels) of the skip ellipse's bounding box; ex < 0: never blended
  T color[3];
  T depth;
  int bx0, by0, bx1, by1;  // tile-local pixel box [bx0, bx1) x [by0, by1) that can be hit
};

// Per-Gaussian part of the PackedSplat of every Gaussian with intersections (the tile box is
// left to gather_splats), computed once per call instead of once per intersection.
template <typename T>
std::unique_ptr<PackedSplat<T>[]> pack_gaussians(const RasterParams<T>& p) {
  std::unique_ptr<PackedSplat<T>[]> recs(new PackedSplat<T>[p.N]);
  parallel_items(p.N, [&](int64_t g) {
    if (p.bins.entry_offsets[g + 1] == p.bins.entry_offsets[g]) return;
    PackedSplat<T>& s = recs[g];
    s.conic = {p.conics[3 * g], p.conics[3 * g + 1], p.conics[3 * g + 2]};
    s.mx = p.means2d[2 * g];
    s.my = p.means2d[2 * g + 1];
    s.opacity = p.opacities[g];
    s.skip_power = splat_skip_power(s.opacity);
    s.a_r2 = T(-2) * s.skip_power * s.conic.a;
    s.det = s.conic.a * s.conic.c - s.conic.b * s.conic.b;
    s.inv_a = T(1) / s.conic.a;
    s.b_over_a = s.conic.b * s.inv_a;
    if (!splat_extent(s.conic, s.skip_power, s.ex, s.ey)) s.ex = s.ey = T(-1);
    for (int c = 0; c < 3; ++c) s.color[c] = p.colors ? p.colors[3 * g + c] : T(0);
    s.depth = p.depths ? p.depths[g] : T(0);
  });
  return recs;
}

struct TileView {
  int x0, y0, x1, y1;  // pixel bounds [x0, x1) x [y0, y1)
  int32_t start, end;  // range in the intersection list
};

template <typename T>
GSW_CPU_INLINE TileView tile_view(const RasterParams<T>& p, int64_t tile) {
  const int tx = static_cast<int>(tile % p.bins.tiles_x), ty = static_cast<int>(tile / p.bins.tiles_x);
  TileView v;
  v.x0 = tx * TILE_SIZE;
  v.y0 = ty * TILE_SIZE;
  v.x1 = std::min(v.x0 + TILE_SIZE, p.width);
  v.y1 = std::min(v.y0 + TILE_SIZE, p.height);
  v.start = p.bins.tile_offsets[tile];
  v.end = p.bins.tile_offsets[tile + 1];
  return v;
}

// Tile-local range of pixel indices whose centres (i + 0.5) lie in [c - e, c + e].
template <typename T>
GSW_CPU_INLINE void pixel_range(T c, T e, int lo, int hi, int& out_lo, int& out_hi) {
  const T a = std::max(T(lo), std::min(T(hi), ceil(c - e - T(0.5))));
  const T b = std::max(T(lo), std::min(T(hi), floor(c + e - T(0.5)) + T(1)));
  out_lo = static_cast<int>(a) - lo;
  out_hi = static_cast<int>(b) - lo;
}

// Copies the tile's splats front to back from their records, with the tile-local box each one
// can touch.
template <typename T>
GSW_CPU_INLINE void gather_splats(const RasterParams<T>& p, const PackedSplat<T>* recs,
                                  const TileView& v, std::vector<PackedSplat<T>>& out) {
  out.resize(v.end - v.start);
  constexpr int kAhead = 8;  // records are read in random order: prefetch a few ahead
  for (int32_t k = v.start; k < v.end; ++k) {
    if (k + kAhead < v.end) {
      const char* next = reinterpret_cast<const char*>(recs + p.bins.gauss_ids[k + kAhead]);
      __builtin_prefetch(next);
      __builtin_prefetch(next + sizeof(PackedSplat<T>) - 1);
    }
    PackedSplat<T>& s = out[k - v.start];
    s = recs[p.bins.gauss_ids[k]];
    if (s.ex >= T(0)) {
      pixel_range(s.mx, s.ex, v.x0, v.x1, s.bx0, s.bx1);
      pixel_range(s.my, s.ey, v.y0, v.y1, s.by0, s.by1);
    } else {
      s.bx0 = s.bx1 = s.by0 = s.by1 = 0;
    }
  }
}

// Pixels of a row evaluated together: one 8-lane block (an AVX2 float vector); blocks a splat
// cannot reach, or whose pixels are all finished, are skipped.
constexpr int kLaneBlock = 8;
// A block starts at the first lane of a splat's chord, so it may run up to kLaneBlock - 1 lanes
// past the row (into the next row, or past the tile: tile arrays are padded). Lanes past the
// chord are masked. Per-splat sums are accumulated per lane q of the block.
constexpr int kTileAlloc = kTilePixels + kLaneBlock;
// Margin (pixels) of the row chords against rounding (the chord is otherwise exact, like the box).
constexpr double kChordMargin = 1e-2;

// Tile-local x range [lo[ly], hi[ly]) of each tile row ly that splat s can reach: the pixel
// centres on the chord of its skip ellipse at the row's pixel-centre height (widened by
// kChordMargin), within its box [bx0, bx1). Lanes outside it would compute alpha = 0 (the ellipse is conservative by
// SKIP_LOG_MARGIN), so leaving them out changes no result. All TILE_SIZE rows in one SIMD loop;
// NaN-safe (falls back to the box).
template <typename T>
GSW_CPU_INLINE void row_spans(const PackedSplat<T>& s, T x_centre0, T y_centre0, int32_t* lo,
                              int32_t* hi) {
  const T box0 = T(s.bx0), box1 = T(s.bx1);
  for (int ly = 0; ly < TILE_SIZE; ++ly) {
    const T dy = s.my - (y_centre0 + T(ly));
    const T disc = s.a_r2 - s.det * dy * dy;
    const T half = sqrt(disc > T(0) ? disc : T(0)) * s.inv_a + T(kChordMargin);
    const T mid = s.mx + s.b_over_a * dy - x_centre0;
    const T l = ceil(mid - half), h = floor(mid + half) + T(1);
    const T lc = l > box0 ? (l < box1 ? l : box1) : box0;
    const T hc = h < box1 ? (h > lc ? h : lc) : box1;
    lo[ly] = static_cast<int32_t>(lc);
    hi[ly] = static_cast<int32_t>(hc);
  }
}

// Whether any of a block's kLaneBlock flags is set.
GSW_CPU_INLINE bool any_set(const int32_t* flags) {
  int32_t any = 0;
  for (int q = 0; q < kLaneBlock; ++q) any |= flags[q];
  return any != 0;
}

// One lane block of a row for one splat, front to back (fixed trip count, so the loop becomes
// straight-line SIMD together with `pixel_fn`); lanes from hi on are masked. Per pixel:
// w = blending weight (0 when masked, skipped, finished or terminating here), passed to
// pixel_fn(q, w) in the same loop, and updates of the transmittance, liveness and
// last-contributor arrays (indexed by the lane q).
template <typename T, typename F>
GSW_CPU_INLINE void blend_lanes(const PackedSplat<T>& s, int j, T x_centre0, T pyc, int hi, T* tr,
                                int32_t* alive, int32_t* last, F&& pixel_fn) {
  for (int q = 0; q < kLaneBlock; ++q) {
    const T power = gaussian_power(s.conic, s.mx, s.my, x_centre0 + T(q), pyc);
    const T alpha0 = splat_alpha(s.opacity, power);
    const bool open = (alive[q] != 0) & (q < hi);
    const T alpha = open ? alpha0 : T(0);
    const bool term = (alpha > T(0)) & blend_terminates(tr[q], alpha);
    alive[q] = term ? 0 : alive[q];
    const T a = term ? T(0) : alpha;
    pixel_fn(q, a * tr[q]);
    tr[q] *= T(1) - a;
    last[q] = a > T(0) ? j + 1 : last[q];
  }
}

// Every kAliveCheckInterval splats, a tile checks whether any of its pixels is still open.
constexpr int kAliveCheckInterval = 16;

// Front-to-back traversal of one tile, splat-major over the lane blocks each splat can reach:
// identical decisions to a per-pixel loop. Calls pixel_fn(j, k, q, w) for every lane q of every
// visited block of splat j (k: tile-local flat pixel index < kTileAlloc; w = 0 where it does not
// blend) and splat_end(j) after its last row. `tr` and `last` hold kTileAlloc values.
template <typename T, typename F, typename G>
GSW_CPU_INLINE void traverse_front_to_back(const TileView& v, const std::vector<PackedSplat<T>>& splats, T* tr,
                            int32_t* last, F&& pixel_fn, G&& splat_end) {
  int32_t alive[kTileAlloc];
  for (int k = 0; k < kTileAlloc; ++k) {
    tr[k] = T(1);
    last[k] = alive[k] = 0;
  }
  // Pixels outside the image (partial tiles) are never open.
  for (int ly = 0; ly < TILE_SIZE; ++ly)
    for (int lx = 0; lx < TILE_SIZE; ++lx)
      alive[ly * TILE_SIZE + lx] = (lx < v.x1 - v.x0 && ly < v.y1 - v.y0) ? 1 : 0;
  const int n = static_cast<int>(splats.size());
  const T x_centre0 = T(v.x0) + T(0.5), y_centre0 = T(v.y0) + T(0.5);
  int32_t span_lo[TILE_SIZE], span_hi[TILE_SIZE];
  for (int j = 0; j < n; ++j) {
    if (j % kAliveCheckInterval == 0) {
      int open = 0;
      for (int k = 0; k < kTilePixels; ++k) open |= alive[k];
      if (!open) break;
    }
    const PackedSplat<T>& s = splats[j];
    row_spans(s, x_centre0, y_centre0, span_lo, span_hi);
    for (int ly = s.by0; ly < s.by1; ++ly) {
      const T pyc = y_centre0 + T(ly);
      const int lo = span_lo[ly], hi = span_hi[ly];
      for (int b0 = lo; b0 < hi; b0 += kLaneBlock) {
        const int k0 = ly * TILE_SIZE + b0;
        if (!any_set(alive + k0)) continue;
        blend_lanes(s, j, x_centre0 + T(b0), pyc, hi - b0, tr + k0, alive + k0, last + k0,
                    [&](int q, T w) { pixel_fn(j, ly * TILE_SIZE + b0 + q, q, w); });
      }
    }
    if (s.by1 > s.by0) splat_end(j);
  }
}

// Reduces a splat's per-lane sums (`k_sums` rows, then one row of maxima) into its record and
// clears them.
template <typename T>
GSW_CPU_INLINE void flush_lanes(int k_sums, T* __restrict lanes, T* __restrict r) {
  for (int k = 0; k < k_sums; ++k) {
    T acc = T(0);
    for (int q = 0; q < kLaneBlock; ++q) acc += lanes[k * kLaneBlock + q];
    r[k] += acc;
  }
  T m = r[k_sums];
  for (int q = 0; q < kLaneBlock; ++q) m = m < lanes[k_sums * kLaneBlock + q] ? lanes[k_sums * kLaneBlock + q] : m;
  r[k_sums] = m;
  for (int k = 0; k < (k_sums + 1) * kLaneBlock; ++k) lanes[k] = T(0);
}

// Contribution traversal of one tile with CC weight channels (CC in 1..3 unrolled; CC = 0: C at
// run time).
template <typename T, int CC>
GSW_CPU_KERNEL void contribution_tile(const TileView& v, const std::vector<PackedSplat<T>>& splats, int C,
                       const T* __restrict wmap, T* __restrict lane, T* out) {
  const int nc = CC > 0 ? CC : C;
  const int S = nc + 2;
  T* __restrict hits = lane + nc * kLaneBlock;
  T* __restrict mx = hits + kLaneBlock;
  T tr[kTileAlloc];
  int32_t last[kTileAlloc];
  traverse_front_to_back(
      v, splats, tr, last,
      [&](int, int k, int q, T w) {
        if constexpr (CC >= 1) lane[q] += wmap[k] * w;  // unrolled: the loop stays vectorizable
        if constexpr (CC >= 2) lane[kLaneBlock + q] += wmap[kTileAlloc + k] * w;
        if constexpr (CC >= 3) lane[2 * kLaneBlock + q] += wmap[2 * kTileAlloc + k] * w;
        if constexpr (CC == 0)
          for (int ch = 0; ch < nc; ++ch) lane[ch * kLaneBlock + q] += wmap[ch * kTileAlloc + k] * w;
        // Select-free forms (selects here stop the vectorizer): w is in [0, 1], so ceil(w) is
        // the hit indicator; max(a, b) = (a + b + |a - b|) / 2 (exact up to one rounding).
        hits[q] += ceil(w);
        mx[q] = T(0.5) * (mx[q] + w + std::abs(mx[q] - w));
      },
      [&](int j) { flush_lanes(nc + 1, lane, out + int64_t(S) * j); });
}

// Forward blending of one tile (`splats`: reusable per-thread storage).
template <typename T>
GSW_CPU_KERNEL void forward_tile(const RasterParams<T>& p, const PackedSplat<T>* recs, int64_t tile,
                                 std::vector<PackedSplat<T>>& splats) {
  const int64_t P = int64_t(p.width) * p.height;
  const TileView v = tile_view(p, tile);
  gather_splats(p, recs, v, splats);
  T tr[kTileAlloc], col[3][kTileAlloc], dep[kTileAlloc];
  int32_t last[kTileAlloc];
  for (int k = 0; k < kTileAlloc; ++k) col[0][k] = col[1][k] = col[2][k] = dep[k] = T(0);
  const PackedSplat<T>* sp = splats.data();  // no TLS lookup in the lambda
  traverse_front_to_back(v, splats, tr, last, [&](int j, int k, int, T w) {
    const PackedSplat<T>& s = sp[j];
    col[0][k] += w * s.color[0];
    col[1][k] += w * s.color[1];
    col[2][k] += w * s.color[2];
    dep[k] += w * s.depth;
  }, [](int) {});
  for (int py = v.y0; py < v.y1; ++py) {
    for (int px = v.x0; px < v.x1; ++px) {
      const int k = (py - v.y0) * TILE_SIZE + (px - v.x0);
      const int64_t pix = int64_t(py) * p.width + px;
      for (int c = 0; c < 3; ++c) p.image[c * P + pix] = col[c][k] + tr[k] * p.background[c];
      p.alpha[pix] = T(1) - tr[k];
      p.depth[pix] = dep[k];
      p.final_T[pix] = tr[k];
      p.n_contrib[pix] = last[k];
    }
  }
}

// Per-pixel state of one tile's backward walk (tile-local, kTileAlloc entries, pads inert), walking
// back to front from each pixel's last blended splat.
template <typename T>
struct BackwardPixels {
  T tr[kTileAlloc], t_final[kTileAlloc], v_tfinal[kTileAlloc];
  T vi[3][kTileAlloc], vd[kTileAlloc];
  T behind[3][kTileAlloc], behind_d[kTileAlloc];  // colour/depth behind, per unit T
  int32_t n_pix[kTileAlloc];
  // Largest n_contrib of each aligned group of kLaneBlock pixels: splat j touches no pixel of a
  // block whose group has a maximum <= j.
  int32_t blk_n[kTileAlloc / kLaneBlock];
  int max_n;  // largest n_contrib of the tile
};

template <typename T>
GSW_CPU_INLINE void load_backward_pixels(const RasterParams<T>& p, const RasterGradParams<T>& g,
                                         const TileView& v, BackwardPixels<T>& px) {
  const int64_t P = int64_t(p.width) * p.height;
  px.max_n = 0;
  for (int k = 0; k < kTileAlloc; ++k) {
    px.n_pix[k] = 0;
    px.tr[k] = px.t_final[k] = px.v_tfinal[k] = px.vd[k] = px.behind_d[k] = T(1);
    for (int c = 0; c < 3; ++c) px.vi[c][k] = px.behind[c][k] = T(0);
  }
  for (int py = v.y0; py < v.y1; ++py) {
    for (int x = v.x0; x < v.x1; ++x) {
      const int k = (py - v.y0) * TILE_SIZE + (x - v.x0);
      const int64_t pix = int64_t(py) * p.width + x;
      px.n_pix[k] = p.n_contrib[pix];
      px.max_n = std::max(px.max_n, px.n_pix[k]);
      px.tr[k] = px.t_final[k] = p.final_T[pix];
      for (int c = 0; c < 3; ++c) px.vi[c][k] = g.v_image[c * P + pix];
      px.vd[k] = g.v_depth ? g.v_depth[pix] : T(0);
      px.behind_d[k] = T(0);
      // d(loss)/d(T_final): background and the alpha output (alpha = 1 - T_final).
      px.v_tfinal[k] = px.vi[0][k] * p.background[0] + px.vi[1][k] * p.background[1] +
                       px.vi[2][k] * p.background[2] - (g.v_alpha ? g.v_alpha[pix] : T(0));
    }
  }
  for (int k = 0; k < kTileAlloc / kLaneBlock; ++k) {
    int32_t m = 0;
    for (int q = 0; q < kLaneBlock; ++q) m = std::max(m, px.n_pix[k * kLaneBlock + q]);
    px.blk_n[k] = m;
  }
}

// Backward of splat j over the aligned lane block at tile-local pixel k0 (pixel centres pxc0 + q,
// pyc; lanes outside [qlo, qhi) masked): steps the block's pixels back over splat j and adds the
// splat's cotangents per lane slot to l (rows in kSplatGradSize record order).
template <typename T>
GSW_CPU_INLINE void backward_block(const PackedSplat<T>& s, int j, BackwardPixels<T>& px, int k0, T pxc0,
                                   T pyc, int qlo, int qhi, T (&l)[kSplatGradSize][kLaneBlock]) {
  T* trr = px.tr + k0;
  const T* tf = px.t_final + k0;
  const T* vtf = px.v_tfinal + k0;
  const T *v0 = px.vi[0] + k0, *v1 = px.vi[1] + k0, *v2 = px.vi[2] + k0, *vdr = px.vd + k0;
  T *b0r = px.behind[0] + k0, *b1r = px.behind[1] + k0, *b2r = px.behind[2] + k0;
  T* bd = px.behind_d + k0;
  const int32_t* np = px.n_pix + k0;
  for (int q = 0; q < kLaneBlock; ++q) {  // fixed trip count; lanes outside [qlo, qhi) masked
    const T pxc = pxc0 + T(q);
    const T power = gaussian_power(s.conic, s.mx, s.my, pxc, pyc);
    const T G = splat_gaussian(power);
    const T alpha0 = splat_alpha_from_gaussian(s.opacity, power, G);
    const bool open = (j < np[q]) & (q >= qlo) & (q < qhi);
    const T a = open ? alpha0 : T(0);
    const T om = T(1) - a;
    const T inv_om = T(1) / om;
    const T t = trr[q] * inv_om;  // transmittance in front of splat j (unchanged if a = 0)
    trr[q] = t;
    const T w = a * t;
    l[6][q] += w * v0[q];
    l[7][q] += w * v1[q];
    l[8][q] += w * v2[q];
    l[9][q] += w * vdr[q];
    T v_alpha = t * ((s.color[0] - b0r[q]) * v0[q] + (s.color[1] - b1r[q]) * v1[q] +
                     (s.color[2] - b2r[q]) * v2[q] + (s.depth - bd[q]) * vdr[q]) -
                tf[q] * inv_om * vtf[q];
    v_alpha = a > T(0) ? v_alpha : T(0);
    const SplatGrad<T> sg = splat_alpha_vjp_from_gaussian(s.conic, s.mx - pxc, s.my - pyc, G, s.opacity, v_alpha);
    l[0][q] += sg.mean2d.x;
    l[1][q] += sg.mean2d.y;
    l[2][q] += sg.conic.a;
    l[3][q] += sg.conic.b;
    l[4][q] += sg.conic.c;
    l[5][q] += sg.opacity;
    b0r[q] = a * s.color[0] + om * b0r[q];
    b1r[q] = a * s.color[1] + om * b1r[q];
    b2r[q] = a * s.color[2] + om * b2r[q];
    bd[q] = a * s.depth + om * bd[q];
  }
}

// Backward blending of one tile: per-splat cotangent records into scratch[slot].
template <typename T>
GSW_CPU_KERNEL void backward_tile(const RasterParams<T>& p, const RasterGradParams<T>& g,
                                  const PackedSplat<T>* recs, int64_t tile,
                                  std::vector<PackedSplat<T>>& splats, T* scratch) {
  constexpr int S = kSplatGradSize;
  const TileView v = tile_view(p, tile);
  gather_splats(p, recs, v, splats);
  T* out = scratch + int64_t(S) * v.start;
  BackwardPixels<T> px;
  load_backward_pixels(p, g, v, px);
  // Records of splats no pixel reaches are zero; the others are written once, below.
  std::fill(out + int64_t(S) * px.max_n, out + int64_t(S) * (v.end - v.start), T(0));
  const T x_centre0 = T(v.x0) + T(0.5), y_centre0 = T(v.y0) + T(0.5);
  int32_t span_lo[TILE_SIZE], span_hi[TILE_SIZE];
  T l[S][kLaneBlock];  // per-lane-slot partial sums of one splat's cotangents
  for (int j = px.max_n - 1; j >= 0; --j) {
    const PackedSplat<T>& s = splats[j];
    for (int k = 0; k < S; ++k)
      for (int q = 0; q < kLaneBlock; ++q) l[k][q] = T(0);
    row_spans(s, x_centre0, y_centre0, span_lo, span_hi);
    for (int ly = s.by0; ly < s.by1; ++ly) {
      const int lo = span_lo[ly], hi = span_hi[ly];
      for (int b0 = lo - lo % kLaneBlock; b0 < hi; b0 += kLaneBlock) {
        const int k0 = ly * TILE_SIZE + b0;
        if (j < px.blk_n[k0 / kLaneBlock])
          backward_block(s, j, px, k0, x_centre0 + T(b0), y_centre0 + T(ly), lo - b0, hi - b0, l);
      }
    }
    T* r = out + int64_t(S) * j;
    for (int k = 0; k < S; ++k) {
      T acc = T(0);
      for (int q = 0; q < kLaneBlock; ++q) acc += l[k][q];
      r[k] = acc;
    }
  }
}

}  // namespace

template <typename T>
void rasterize_forward(const RasterParams<T>& p) {
  const int64_t num_tiles = int64_t(p.bins.tiles_x) * p.bins.tiles_y;
  const auto recs = pack_gaussians(p);
  parallel_dynamic(num_tiles, [&](int64_t tile) {
    thread_local std::vector<PackedSplat<T>> splats;
    forward_tile(p, recs.get(), tile, splats);
  });
}

template <typename T>
void rasterize_backward(const RasterParams<T>& p, const RasterGradParams<T>& g, T* scratch) {
  constexpr int S = kSplatGradSize;
  const int64_t num_tiles = int64_t(p.bins.tiles_x) * p.bins.tiles_y;
  const auto recs = pack_gaussians(p);
  parallel_dynamic(num_tiles, [&](int64_t tile) {
    thread_local std::vector<PackedSplat<T>> splats;
    backward_tile(p, g, recs.get(), tile, splats, scratch);
  });
  parallel_items(p.N, [&](int64_t i) {
    T acc[S];
    for (int k = 0; k < S; ++k) acc[k] = T(0);
    for (int32_t e = p.bins.entry_offsets[i]; e < p.bins.entry_offsets[i + 1]; ++e) {
      const T* r = scratch + int64_t(S) * p.bins.entry_slots[e];
      for (int k = 0; k < S; ++k) acc[k] += r[k];
    }
    g.v_means2d[2 * i] = acc[0];
    g.v_means2d[2 * i + 1] = acc[1];
    for (int k = 0; k < 3; ++k) g.v_conics[3 * i + k] = acc[2 + k];
    g.v_opacities[i] = acc[5];
    for (int k = 0; k < 3; ++k) g.v_colors[3 * i + k] = acc[6 + k];
    g.v_depths[i] = acc[9];
  });
}

template <typename T>
void contribution(const RasterParams<T>& p, const ContributionParams<T>& c, T* scratch) {
  const int64_t P = int64_t(p.width) * p.height;
  const int64_t num_tiles = int64_t(p.bins.tiles_x) * p.bins.tiles_y;
  const int C = c.C;
  const int S = C + 2;  // C weighted sums, hit count, max weight
  const auto recs = pack_gaussians(p);
  parallel_dynamic(num_tiles, [&](int64_t tile) {
    thread_local std::vector<PackedSplat<T>> splats;
    thread_local std::vector<T> wts, lanes;
    const TileView v = tile_view(p, tile);
    gather_splats(p, recs.get(), v, splats);
    T* out = scratch + int64_t(S) * v.start;
    std::fill(out, out + int64_t(S) * splats.size(), T(0));
    // Tile-local copy of the weight map, [C][kTileAlloc] (zero padded).
    wts.assign(size_t(C) * kTileAlloc, T(0));
    for (int py = v.y0; py < v.y1; ++py)
      for (int px = v.x0; px < v.x1; ++px)
        for (int ch = 0; ch < C; ++ch)
          wts[size_t(ch) * kTileAlloc + (py - v.y0) * TILE_SIZE + (px - v.x0)] =
              c.weights[ch * P + int64_t(py) * p.width + px];
    // Per-lane partial sums of the current splat, [C + 2][kLaneBlock], flushed after its last row.
    // (Plain pointers: thread_local access inside the hot lambdas would cost a TLS lookup.)
    lanes.assign(size_t(S) * kLaneBlock, T(0));
    if (C == 1)
      contribution_tile<T, 1>(v, splats, C, wts.data(), lanes.data(), out);
    else if (C == 3)
      contribution_tile<T, 3>(v, splats, C, wts.data(), lanes.data(), out);
    else
      contribution_tile<T, 0>(v, splats, C, wts.data(), lanes.data(), out);
  });
  // Hit counts are exact in T (a record counts at most TILE_SIZE^2 pixels).
  parallel_items(p.N, [&](int64_t i) {
    T hits = T(0), mx = T(0);
    T* v = c.contribution + int64_t(C) * i;
    for (int ch = 0; ch < C; ++ch) v[ch] = T(0);
    for (int32_t e = p.bins.entry_offsets[i]; e < p.bins.entry_offsets[i + 1]; ++e) {
      const T* r = scratch + int64_t(S) * p.bins.entry_slots[e];
      for (int ch = 0; ch < C; ++ch) v[ch] += r[ch];
      hits += r[C];
      mx = std::max(mx, r[C + 1]);
    }
    c.hits[i] = static_cast<int32_t>(hits);
    c.max_weight[i] = mx;
  });
}

template void rasterize_forward<float>(const RasterParams<float>&);
template void rasterize_forward<double>(const RasterParams<double>&);
template void rasterize_backward<float>(const RasterParams<float>&, const RasterGradParams<float>&,
                                        float*);
template void rasterize_backward<double>(const RasterParams<double>&, const RasterGradParams<double>&,
                                         double*);
template void contribution<float>(const RasterParams<float>&, const ContributionParams<float>&, float*);
template void contribution<double>(const RasterParams<double>&, const ContributionParams<double>&,
                                   double*);

}  // namespace gsw::cpu
