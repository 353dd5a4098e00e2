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
#include "cpu/simd.h"

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
      pixel_span(s.mx, s.ex, v.x0, v.x1, s.bx0, s.bx1);
      pixel_span(s.my, s.ey, v.y0, v.y1, s.by0, s.by1);
    } else {
      s.bx0 = s.bx1 = s.by0 = s.by1 = 0;
    }
  }
}

// Pixels of a row evaluated together: one aligned block of kLaneBlock = kLanes pixels (a lane
// vector, cpu/simd.h); blocks a splat cannot reach, or whose reachable pixels are all finished,
// are skipped. Tile rows hold TILE_SIZE / kLaneBlock whole blocks.
constexpr int kLaneBlock = kLanes;
static_assert(TILE_SIZE % kLaneBlock == 0, "tile rows must hold whole lane blocks");
// Tile-local arrays hold kTileAlloc values (one spare block).
constexpr int kTileAlloc = kTilePixels + kLaneBlock;
// Margin (pixels) of the row chords against rounding (the chord is otherwise exact, like the box).
constexpr double kChordMargin = 1e-2;

// A set of pixels of one tile row: bit lx stands for tile-local column lx.
using RowBits = uint32_t;
static_assert(TILE_SIZE < 32, "a tile row must fit a RowBits");

// The pixels of each tile row ly that splat s can reach, as RowBits: the pixel centres on the
// chord of its skip ellipse at the row's pixel-centre height (widened by kChordMargin), within
// its box [bx0, bx1). Lanes outside it would compute alpha = 0 (the ellipse is conservative by
// SKIP_LOG_MARGIN), so leaving them out changes no result. All TILE_SIZE rows in one SIMD loop;
// NaN-safe (falls back to the box).
template <typename T>
GSW_CPU_INLINE void row_spans(const PackedSplat<T>& s, T x_centre0, T y_centre0, RowBits* span) {
  const T box0 = T(s.bx0), box1 = T(s.bx1);
  for (int ly = 0; ly < TILE_SIZE; ++ly) {
    const T dy = s.my - (y_centre0 + T(ly));
    const T disc = s.a_r2 - s.det * dy * dy;
    const T half = sqrt(disc > T(0) ? disc : T(0)) * s.inv_a + T(kChordMargin);
    const T mid = s.mx + s.b_over_a * dy - x_centre0;
    const T l = ceil(mid - half), h = floor(mid + half) + T(1);
    const T lc = l > box0 ? (l < box1 ? l : box1) : box0;
    const T hc = h < box1 ? (h > lc ? h : lc) : box1;  // lc <= hc
    span[ly] = (RowBits(1) << static_cast<int32_t>(hc)) - (RowBits(1) << static_cast<int32_t>(lc));
  }
}

// A splat's parameters broadcast to lane vectors.
template <typename T>
struct SplatLanes {
  Sym2<VecT<T>> conic;
  VecT<T> mx, my, opacity;
  explicit GSW_CPU_INLINE SplatLanes(const PackedSplat<T>& s)
      : conic{splat(s.conic.a), splat(s.conic.b), splat(s.conic.c)},
        mx(splat(s.mx)),
        my(splat(s.my)),
        opacity(splat(s.opacity)) {}
};

constexpr int kTileBlocks = kTilePixels / kLaneBlock;

// One lane block of a splat's traversal, packed: the block's index (its first pixel is
// kLaneBlock * index) and its lanes to evaluate (bit q: pixel kLaneBlock * index + q).
struct LaneBlock {
  uint32_t packed;  // index << kLaneBlock | lanes
  GSW_CPU_INLINE int index() const { return static_cast<int>(packed >> kLaneBlock); }
  GSW_CPU_INLINE int k0() const { return index() * kLaneBlock; }
  GSW_CPU_INLINE uint32_t lanes() const { return packed & ((1u << kLaneBlock) - 1); }
};

// Pixel-centre coordinates of the first pixel of each lane block of a tile.
template <typename T>
struct BlockCentres {
  T x[kTileBlocks], y[kTileBlocks];
  GSW_CPU_INLINE BlockCentres(T x_centre0, T y_centre0) {
    for (int b = 0; b < kTileBlocks; ++b) {
      x[b] = x_centre0 + T(b * kLaneBlock % TILE_SIZE);
      y[b] = y_centre0 + T(b * kLaneBlock / TILE_SIZE);
    }
  }
};

// The blocks of splat s's rows [by0, by1) that hold a pixel both on its chord (`span`, from
// row_spans) and in `live`, in row-major order, with those pixels as their lanes. Returns their
// number (`blocks` holds kTileBlocks).
template <typename T>
GSW_CPU_INLINE int collect_blocks(const PackedSplat<T>& s, const RowBits* span, const RowBits* live,
                                  LaneBlock* blocks) {
  constexpr RowBits kBlockBits = (RowBits(1) << kLaneBlock) - 1;
  constexpr int kRowBlocks = TILE_SIZE / kLaneBlock;
  int nb = 0;
  for (int ly = s.by0; ly < s.by1; ++ly) {
    const RowBits m = span[ly] & live[ly];
    for (int rb = 0; rb < kRowBlocks; ++rb) {
      const uint32_t lanes = (m >> (rb * kLaneBlock)) & kBlockBits;
      blocks[nb] = LaneBlock{uint32_t(ly * kRowBlocks + rb) << kLaneBlock | lanes};  // kept if lanes != 0
      nb += lanes != 0;
    }
  }
  return nb;
}

// Blends splat j over NB lane blocks at once (independent work the CPU can overlap: a block
// alone is one long dependency chain, exp() included). Per lane (open: one of the block's lanes
// and tr > 0): w = blending weight (0 where not open, skipped or terminating here), passed to
// pixel_fn(j, k0, w), then the transmittance (negated where the pixel terminates) and
// last-contributor updates.
template <int NB, typename T, typename F>
GSW_CPU_INLINE void blend_blocks(const SplatLanes<T>& sl, const BlockCentres<T>& cen, const LaneBlock* blk, int j,
                                 T* tr, int32_t* last, F& pixel_fn) {
  using V = VecT<T>;
  V t[NB], a[NB];
  MaskT<T> term[NB];
  for (int b = 0; b < NB; ++b) {
    const int i = blk[b].index();
    t[b] = load<V>(tr + blk[b].k0());
    const V power = gaussian_power(sl.conic, sl.mx, sl.my, cen.x[i] + iota<T>(), splat(cen.y[i]));
    const MaskT<T> open = mask_as<T>(bits_mask(blk[b].lanes())) & (t[b] > T(0));
    const V alpha = open ? splat_alpha(sl.opacity, power) : T(0);
    term[b] = (alpha > T(0)) & blend_terminates(t[b], alpha);
    a[b] = term[b] ? T(0) : alpha;
  }
  const VecI32 next = VecI32{} + (j + 1);
  for (int b = 0; b < NB; ++b) {
    const int k0 = blk[b].k0();
    pixel_fn(j, k0, a[b] * t[b]);
    store(tr + k0, term[b] ? -t[b] : t[b] * (T(1) - a[b]));
    store(last + k0, mask_i32(a[b] > T(0)) ? next : load<VecI32>(last + k0));
  }
}

// Every kLiveRefreshInterval splats, a tile marks its open pixels (tr > 0) in `live` (blocks
// with no live pixel are skipped; blocks of pixels that finished since are blended with those
// lanes masked) and stops when none is left.
constexpr int kLiveRefreshInterval = 16;

// Sets live[ly] to the open pixels (tr > 0) of each tile row; returns whether there are any.
template <typename T>
GSW_CPU_INLINE bool refresh_live(const T* tr, RowBits* live) {
  RowBits any = 0;
  for (int ly = 0; ly < TILE_SIZE; ++ly) {
    RowBits m = 0;
    for (int b0 = 0; b0 < TILE_SIZE; b0 += kLaneBlock)
      m |= RowBits(lane_bits(mask_i32(load<VecT<T>>(tr + ly * TILE_SIZE + b0) > T(0)))) << b0;
    live[ly] = m;
    any |= m;
  }
  return any != 0;
}

// Front-to-back traversal of one tile, splat-major over the aligned lane blocks each splat can
// reach: identical decisions to a per-pixel loop. Calls pixel_fn(j, k0, w) for every visited
// block of splat j (k0: tile-local flat index of the block's first pixel; w: the lane vector of
// blending weights, 0 where the splat does not blend) and splat_end(j) after its last block.
// `tr` and `last` hold kTileAlloc values: on return, tr holds each pixel's transmittance,
// negated once the pixel has finished (pixels outside the image: -1), and last its n_contrib.
template <typename T, typename F, typename G>
GSW_CPU_INLINE void traverse_front_to_back(const TileView& v, const std::vector<PackedSplat<T>>& splats, T* tr,
                            int32_t* last, F&& pixel_fn, G&& splat_end) {
  // Open pixels hold tr > 0, finished ones -tr (tr >= T_MIN > 0 while open).
  for (int k = 0; k < kTileAlloc; ++k) {
    const int lx = k % TILE_SIZE, ly = k / TILE_SIZE;
    tr[k] = (lx < v.x1 - v.x0 && ly < v.y1 - v.y0) ? T(1) : T(-1);
    last[k] = 0;
  }
  const int n = static_cast<int>(splats.size());
  const T x_centre0 = T(v.x0) + T(0.5), y_centre0 = T(v.y0) + T(0.5);
  const BlockCentres<T> cen(x_centre0, y_centre0);
  RowBits live[TILE_SIZE], span[TILE_SIZE];
  LaneBlock blocks[kTileBlocks];
  for (int j = 0; j < n; ++j) {
    if (j % kLiveRefreshInterval == 0 && !refresh_live(tr, live)) break;
    const PackedSplat<T>& s = splats[j];
    if (s.by1 <= s.by0) continue;
    row_spans(s, x_centre0, y_centre0, span);
    const int nb = collect_blocks(s, span, live, blocks);
    const SplatLanes<T> sl(s);
    int b = 0;
    for (; b + 4 <= nb; b += 4) blend_blocks<4>(sl, cen, blocks + b, j, tr, last, pixel_fn);
    if (b + 2 <= nb) {
      blend_blocks<2>(sl, cen, blocks + b, j, tr, last, pixel_fn);
      b += 2;
    }
    if (b < nb) blend_blocks<1>(sl, cen, blocks + b, j, tr, last, pixel_fn);
    splat_end(j);
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
  using V = VecT<T>;
  const int nc = CC > 0 ? CC : C;
  const int S = nc + 2;
  T* __restrict hits = lane + nc * kLaneBlock;
  T* __restrict mx = hits + kLaneBlock;
  T tr[kTileAlloc];
  int32_t last[kTileAlloc];
  traverse_front_to_back(
      v, splats, tr, last,
      [&](int, int k0, V w) {
        for (int ch = 0; ch < nc; ++ch)
          store(lane + ch * kLaneBlock, load<V>(lane + ch * kLaneBlock) + load<V>(wmap + ch * kTileAlloc + k0) * w);
        store(hits, load<V>(hits) + (w > T(0) ? T(1) : T(0)));
        const V m = load<V>(mx);
        store(mx, m < w ? w : m);
      },
      [&](int j) { flush_lanes(nc + 1, lane, out + int64_t(S) * j); });
}

// Forward blending of one tile (`splats`: reusable per-thread storage).
template <typename T>
GSW_CPU_KERNEL void forward_tile(const RasterParams<T>& p, const PackedSplat<T>* recs, int64_t tile,
                                 std::vector<PackedSplat<T>>& splats) {
  using V = VecT<T>;
  const int64_t P = int64_t(p.width) * p.height;
  const TileView v = tile_view(p, tile);
  gather_splats(p, recs, v, splats);
  T tr[kTileAlloc], col[3][kTileAlloc], dep[kTileAlloc];
  int32_t last[kTileAlloc];
  for (int k = 0; k < kTileAlloc; ++k) col[0][k] = col[1][k] = col[2][k] = dep[k] = T(0);
  const PackedSplat<T>* sp = splats.data();  // no TLS lookup in the lambda
  traverse_front_to_back(v, splats, tr, last, [&](int j, int k0, V w) {
    const PackedSplat<T>& s = sp[j];
    for (int c = 0; c < 3; ++c) store(col[c] + k0, load<V>(col[c] + k0) + w * s.color[c]);
    store(dep + k0, load<V>(dep + k0) + w * s.depth);
  }, [](int) {});
  for (int py = v.y0; py < v.y1; ++py) {
    for (int px = v.x0; px < v.x1; ++px) {
      const int k = (py - v.y0) * TILE_SIZE + (px - v.x0);
      const int64_t pix = int64_t(py) * p.width + px;
      const T t = std::abs(tr[k]);
      for (int c = 0; c < 3; ++c) p.image[c * P + pix] = col[c][k] + t * p.background[c];
      p.alpha[pix] = T(1) - t;
      p.depth[pix] = dep[k];
      p.final_T[pix] = t;
      p.n_contrib[pix] = last[k];
    }
  }
}

// Per-pixel data of one tile's backward walk (tile-local, kTileAlloc entries, pads inert), walking
// back to front from each pixel's last blended splat: core/math.h's BlendBackwardPixel and
// PixelCotangents of every pixel, field by field.
template <typename T>
struct BackwardPixels {
  T tr[kTileAlloc], behind[4][kTileAlloc];
  T v_color[3][kTileAlloc], v_depth[kTileAlloc], t_final[kTileAlloc], v_t_final[kTileAlloc];
  // The pixels with n_contrib > 0 as n_contrib << 8 | k (k: tile-local index), largest first: the
  // walk adds each one to its set of active pixels on reaching that pixel's last blended splat.
  int32_t order[kTilePixels];
  int n_order;
  int max_n;  // largest n_contrib of the tile
  // Whether any pixel has a nonzero depth / T_final cotangent (otherwise their terms are left out).
  bool has_depth, has_t_final;
};
static_assert(kTilePixels <= 256, "BackwardPixels::order packs the pixel index into 8 bits");

// `count` is reusable per-thread storage (the counting sort of px.order).
template <typename T>
GSW_CPU_INLINE void load_backward_pixels(const RasterParams<T>& p, const RasterGradParams<T>& g,
                                         const TileView& v, BackwardPixels<T>& px, std::vector<int32_t>& count) {
  const int64_t P = int64_t(p.width) * p.height;
  px.max_n = 0;
  px.n_order = 0;
  px.has_depth = px.has_t_final = false;
  for (int k = 0; k < kTileAlloc; ++k) {
    px.tr[k] = px.t_final[k] = T(1);
    px.v_depth[k] = px.v_t_final[k] = T(0);
    for (int c = 0; c < 4; ++c) px.behind[c][k] = T(0);
    for (int c = 0; c < 3; ++c) px.v_color[c][k] = T(0);
  }
  for (int py = v.y0; py < v.y1; ++py) {
    for (int x = v.x0; x < v.x1; ++x) {
      const int k = (py - v.y0) * TILE_SIZE + (x - v.x0);
      const int64_t pix = int64_t(py) * p.width + x;
      const int32_t n = p.n_contrib[pix];
      px.max_n = std::max(px.max_n, n);
      if (n > 0) px.order[px.n_order++] = n << 8 | k;  // sorted below
      px.tr[k] = px.t_final[k] = p.final_T[pix];
      for (int c = 0; c < 3; ++c) px.v_color[c][k] = g.v_image[c * P + pix];
      px.v_depth[k] = g.v_depth ? g.v_depth[pix] : T(0);
      // d(loss)/d(T_final): background and the alpha output (alpha = 1 - T_final).
      px.v_t_final[k] = px.v_color[0][k] * p.background[0] + px.v_color[1][k] * p.background[1] +
                        px.v_color[2][k] * p.background[2] - (g.v_alpha ? g.v_alpha[pix] : T(0));
      px.has_depth |= px.v_depth[k] != T(0);
      px.has_t_final |= px.v_t_final[k] != T(0);
    }
  }
  // Counting sort by n_contrib, largest first (pixel order within one n_contrib does not matter).
  count.assign(px.max_n + 1, 0);
  for (int e = 0; e < px.n_order; ++e) ++count[px.order[e] >> 8];
  for (int n = px.max_n, pos = 0; n > 0; --n) {
    const int c = count[n];
    count[n] = pos;
    pos += c;
  }
  int32_t keys[kTilePixels];
  std::copy(px.order, px.order + px.n_order, keys);
  for (int e = 0; e < px.n_order; ++e) px.order[count[keys[e] >> 8]++] = keys[e];
}

// Backward of splat s (tile-local index j) over NB aligned lane blocks at once (blk[b].lanes: pixels
// on the splat's chord that blended splat j or a splat behind it): steps the blocks' pixels back
// over it (blend_backward_step) and adds its cotangents per lane to l (rows in kBlendGrads
// record order).
template <int NB, bool kDepth, bool kFinalT, typename T>
GSW_CPU_INLINE void backward_blocks(const SplatLanes<T>& sl, const PackedSplat<T>& s, const BlockCentres<T>& cen,
                                    BackwardPixels<T>& px, const LaneBlock* blk, VecT<T>* l) {
  using V = VecT<T>;
  for (int b = 0; b < NB; ++b) {
    const int k0 = blk[b].k0();
    const V pxc = cen.x[blk[b].index()] + iota<T>(), pyc = splat(cen.y[blk[b].index()]);
    PixelCotangents<V> cv{};
    BlendBackwardPixel<V> st{};
    for (int c = 0; c < 3; ++c) {
      cv.color[c] = load<V>(px.v_color[c] + k0);
      st.behind[c] = load<V>(px.behind[c] + k0);
    }
    if constexpr (kDepth) {
      cv.depth = load<V>(px.v_depth + k0);
      st.behind[3] = load<V>(px.behind[3] + k0);
    }
    if constexpr (kFinalT) {
      cv.t_final = load<V>(px.t_final + k0);
      cv.v_t_final = load<V>(px.v_t_final + k0);
    }
    st.tr = load<V>(px.tr + k0);
    const V power = gaussian_power(sl.conic, sl.mx, sl.my, pxc, pyc);
    const V G = splat_gaussian(power);
    const V a = mask_as<T>(bits_mask(blk[b].lanes())) ? splat_alpha_from_gaussian(sl.opacity, power, G) : T(0);
    const BlendGrad<V> g = blend_backward_step<kDepth, kFinalT>(
        SplatAtPixel<V>{sl.conic, sl.mx - pxc, sl.my - pyc, G, sl.opacity, a, {s.color[0], s.color[1], s.color[2]},
                        s.depth},
        cv, st);
    add_blend_grad<kDepth>(g, l);
    store(px.tr + k0, st.tr);
    for (int c = 0; c < 3; ++c) store(px.behind[c] + k0, st.behind[c]);
    if constexpr (kDepth) store(px.behind[3] + k0, st.behind[3]);
  }
}

// The back-to-front walk of one tile over its splats [0, max_n): each splat's cotangent record
// into out (kBlendGrads values per splat).
template <bool kDepth, bool kFinalT, typename T>
GSW_CPU_INLINE void walk_back(const TileView& v, const std::vector<PackedSplat<T>>& splats, BackwardPixels<T>& px,
                              T* out) {
  using V = VecT<T>;
  constexpr int S = kBlendGrads;
  const T x_centre0 = T(v.x0) + T(0.5), y_centre0 = T(v.y0) + T(0.5);
  const BlockCentres<T> cen(x_centre0, y_centre0);
  RowBits active[TILE_SIZE] = {};  // the pixels that blended splat j or a splat behind it
  RowBits span[TILE_SIZE];
  LaneBlock blocks[kTileBlocks];
  int e = 0;
  for (int j = px.max_n - 1; j >= 0; --j) {
    for (; e < px.n_order && (px.order[e] >> 8) > j; ++e) {
      const int k = px.order[e] & 0xff;
      active[k / TILE_SIZE] |= RowBits(1) << (k % TILE_SIZE);
    }
    const PackedSplat<T>& s = splats[j];
    V l[S];  // per-lane partial sums of the splat's cotangents
    for (int k = 0; k < S; ++k) l[k] = V{};
    row_spans(s, x_centre0, y_centre0, span);
    const int nb = collect_blocks(s, span, active, blocks);
    const SplatLanes<T> sl(s);
    int b = 0;
    for (; b + 2 <= nb; b += 2) backward_blocks<2, kDepth, kFinalT>(sl, s, cen, px, blocks + b, l);
    if (b < nb) backward_blocks<1, kDepth, kFinalT>(sl, s, cen, px, blocks + b, l);
    T* r = out + int64_t(S) * j;
    for (int k = 0; k < S; ++k) r[k] = lane_sum(l[k]);
  }
}

// Backward blending of one tile: per-splat cotangent records into scratch[slot - row0] (`splats`,
// `count`: reusable per-thread storage).
template <typename T>
GSW_CPU_KERNEL void backward_tile(const RasterParams<T>& p, const RasterGradParams<T>& g,
                                  const PackedSplat<T>* recs, int64_t tile,
                                  std::vector<PackedSplat<T>>& splats, std::vector<int32_t>& count, T* scratch,
                                  int64_t row0) {
  constexpr int S = kBlendGrads;
  const TileView v = tile_view(p, tile);
  gather_splats(p, recs, v, splats);
  T* out = scratch + int64_t(S) * (v.start - row0);
  BackwardPixels<T> px;
  load_backward_pixels(p, g, v, px, count);
  // Records of splats no pixel reaches are zero; the others are written once, by walk_back.
  std::fill(out + int64_t(S) * px.max_n, out + int64_t(S) * (v.end - v.start), T(0));
  if (px.has_depth && px.has_t_final)
    walk_back<true, true>(v, splats, px, out);
  else if (px.has_depth)
    walk_back<true, false>(v, splats, px, out);
  else if (px.has_t_final)
    walk_back<false, true>(v, splats, px, out);
  else
    walk_back<false, false>(v, splats, px, out);
}

// The per-Gaussian reduction reads each Gaussian's records at their sorted positions, scattered
// over the whole record array (cache misses): it prefetches those of the Gaussian kReduceAhead
// ahead.
constexpr int64_t kReduceAhead = 8;

template <typename T>
GSW_CPU_INLINE void prefetch_records(const TileBins& bins, const T* records, int64_t row0, const SlotSpan& span,
                                     int64_t i, int64_t n) {
  if (i >= n) return;
  for (int32_t e = bins.entry_offsets[i]; e < bins.entry_offsets[i + 1]; ++e) {
    const int32_t s = bins.entry_slots[e];
    if (s < span.lo || s >= span.hi) continue;  // another chunk's record
    const T* r = records + int64_t(kBlendGrads) * (s - row0);
    __builtin_prefetch(r);
    __builtin_prefetch(r + kBlendGrads - 1);
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
void rasterize_backward(const RasterParams<T>& p, const RasterGradParams<T>& g, int64_t budget_rows) {
  const int64_t num_tiles = int64_t(p.bins.tiles_x) * p.bins.tiles_y;
  const int32_t* to = p.bins.tile_offsets;
  // One record per intersection, at its sorted position: a tile's rows are its list range.
  std::vector<std::pair<int64_t, int64_t>> chunks;
  const int64_t max_rows = plan_record_chunks(to, num_tiles, budget_rows, chunks);
  const auto recs = pack_gaussians(p);
  std::unique_ptr<T[]> scratch(new T[size_t(max_rows) * kBlendGrads]);
  const bool chunked = chunks.size() > 1;
  if (chunked) {  // each chunk adds to the gradients
    const size_t n = size_t(p.N);
    std::fill(g.v_means2d, g.v_means2d + 2 * n, T(0));
    std::fill(g.v_conics, g.v_conics + 3 * n, T(0));
    std::fill(g.v_colors, g.v_colors + 3 * n, T(0));
    std::fill(g.v_opacities, g.v_opacities + n, T(0));
    std::fill(g.v_depths, g.v_depths + n, T(0));
  }
  for (const auto& [t0, t1] : chunks) {
    const int64_t row0 = to[t0];
    parallel_dynamic(t1 - t0, [&](int64_t k) {
      thread_local std::vector<PackedSplat<T>> splats;
      thread_local std::vector<int32_t> count;
      backward_tile(p, g, recs.get(), t0 + k, splats, count, scratch.get(), row0);
    });
    const BlendRecords by_slot{nullptr, nullptr, row0};
    const SlotSpan span = chunked ? SlotSpan{to[t0], to[t1], true} : SlotSpan{};
    parallel_items(p.N, [&](int64_t i) {
      prefetch_records(p.bins, scratch.get(), row0, span, i + kReduceAhead, p.N);
      reduce_blend_grads(p.bins, by_slot, scratch.get(), g, i, span);
    });
  }
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
template void rasterize_backward<float>(const RasterParams<float>&, const RasterGradParams<float>&, int64_t);
template void rasterize_backward<double>(const RasterParams<double>&, const RasterGradParams<double>&, int64_t);
template void contribution<float>(const RasterParams<float>&, const ContributionParams<float>&, float*);
template void contribution<double>(const RasterParams<double>&, const ContributionParams<double>&,
                                   double*);

}  // namespace gsw::cpu
