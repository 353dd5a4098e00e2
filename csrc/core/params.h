// Parameter structs of the rasterizer ops: raw pointers and sizes, torch-free, shared by the
// CPU and CUDA backends. The dispatchers in csrc/ops fill them from validated tensors.
//
// Shapes: N Gaussians, K SH coefficients, M (tile, Gaussian) intersections, H x W image,
// P = H * W pixels, C weight channels. Images are channel-major [3, H, W].
#pragma once

#include <cstdint>
#include <utility>
#include <vector>

#include "math.h"

namespace gsw {

// Stage 1: per-Gaussian projection + colour.
template <typename T>
struct ProjectParams {
  int N = 0;
  int K = 0;           // SH coefficients per Gaussian in `sh` (ignored when sh_degree < 0)
  int sh_degree = 0;   // active SH degree; -1: `sh` holds direct RGB colours [N, 3]
  Camera<T> cam{};
  // inputs
  const T* means = nullptr;           // [N, 3] world
  const T* quats = nullptr;           // [N, 4] (w, x, y, z), unnormalised
  const T* log_scales = nullptr;      // [N, 3]
  const T* opacity_logits = nullptr;  // [N]
  const T* sh = nullptr;              // [N, K, 3] or [N, 3] (direct colours)
  // outputs (forward); the backward reads `radii` alone and recomputes the others it needs
  int32_t* radii = nullptr;  // [N] pixel radius, 0 = culled
  T* means2d = nullptr;      // [N, 2] pixels (K p)
  T* conics = nullptr;       // [N, 3] inverse dilated 2-D covariance (a, b, c)
  T* depths = nullptr;       // [N] view-space z
  T* colors = nullptr;       // [N, 3]
  T* opacities = nullptr;    // [N] sigmoid(logit)
  // optional (forward): OR of the bits of nonfinite_fields (core/project.h) over all Gaussians;
  // the caller zeroes it. Null: no check.
  int32_t* nonfinite = nullptr;  // [1]
};

// Cotangents of stage 1: inputs are the per-Gaussian cotangents of the projected quantities,
// outputs the cotangents of the Gaussian parameters.
template <typename T>
struct ProjectGradParams {
  const T* v_means2d = nullptr;    // [N, 2]
  const T* v_conics = nullptr;     // [N, 3]
  const T* v_depths = nullptr;     // [N]
  const T* v_colors = nullptr;     // [N, 3]
  const T* v_opacities = nullptr;  // [N]
  T* v_means = nullptr;            // [N, 3]
  T* v_quats = nullptr;            // [N, 4]
  T* v_log_scales = nullptr;       // [N, 3]
  T* v_opacity_logits = nullptr;   // [N]
  T* v_sh = nullptr;               // [N, K, 3] or [N, 3]
};

// Tile binning inputs: the projected splats (tile_footprint in core/tiles.h decides their tiles).
template <typename T>
struct BinParams {
  int N = 0;
  int tiles_x = 0, tiles_y = 0;
  const T* means2d = nullptr;       // [N, 2]
  const T* conics = nullptr;        // [N, 3]
  const T* opacities = nullptr;     // [N]
  const int32_t* radii = nullptr;   // [N], 0 = culled
  const T* depths = nullptr;        // [N], the sort key
};

// Tile binning result: Gaussians of tile t are gauss_ids[tile_offsets[t] .. tile_offsets[t+1])
// front to back. Intersection e of Gaussian g (e in [entry_offsets[g], entry_offsets[g+1]))
// sits at sorted position entry_slots[e]; this lets per-intersection results be reduced per
// Gaussian in a fixed order (deterministic, no atomics).
struct TileBins {
  int tiles_x = 0, tiles_y = 0;
  int64_t M = 0;
  const int32_t* tile_offsets = nullptr;   // [tiles_x * tiles_y + 1]
  const int32_t* gauss_ids = nullptr;      // [M]
  const int32_t* entry_offsets = nullptr;  // [N + 1]
  const int32_t* entry_slots = nullptr;    // [M]
};

// Stage 2: per-tile alpha blending.
template <typename T>
struct RasterParams {
  int N = 0;
  int width = 0, height = 0;
  TileBins bins{};
  const T* means2d = nullptr;    // [N, 2]
  const T* conics = nullptr;     // [N, 3]
  const T* colors = nullptr;     // [N, 3]
  const T* opacities = nullptr;  // [N]
  const T* depths = nullptr;     // [N]
  const T* background = nullptr; // [3]
  // forward outputs / saved for backward
  T* image = nullptr;            // [3, H, W]
  T* alpha = nullptr;            // [H, W] accumulated opacity 1 - T_final
  T* depth = nullptr;            // [H, W] sum_i w_i z_i (not normalised)
  T* final_T = nullptr;          // [H, W]
  int32_t* n_contrib = nullptr;  // [H, W] 1 + index (in the tile list) of the last blended splat
};

template <typename T>
struct RasterGradParams {
  const T* v_image = nullptr;  // [3, H, W]
  const T* v_alpha = nullptr;  // [H, W] (may be null)
  const T* v_depth = nullptr;  // [H, W] (may be null)
  T* v_means2d = nullptr;      // [N, 2]
  T* v_conics = nullptr;       // [N, 3]
  T* v_colors = nullptr;       // [N, 3]
  T* v_opacities = nullptr;    // [N]
  T* v_depths = nullptr;       // [N]
};

// Where the blend backward keeps its per-intersection records. The backward visits only the front
// of each tile's list: the splats in front of the tile's largest n_contrib (`visited`); the ones
// behind every pixel's last blended splat get no record, neither memory nor time (on scenes of
// large opaque splats that is most of the M intersections). Tile t's records are the rows
// offsets[t] .. offsets[t] + visited[t] - 1 of a [offsets[tiles], kBlendGrads] buffer, in list
// order (CUDA computes visited and its prefix sum before the backward walk). Null pointers: one
// record per intersection at its sorted position, zeros behind the visited front (the CPU's layout:
// its lists are mostly visited, and it then needs no search for an intersection's tile).
//
// A backward whose records would exceed its budget (blend_records_budget) runs in chunks of whole
// tiles: a buffer holds one chunk's records, from row `row0` of the full layout on, and each chunk's
// records are added to the gradients (SlotSpan) before the next chunk reuses the buffer.
struct BlendRecords {
  const int32_t* visited = nullptr;  // [tiles] largest n_contrib of the tile's pixels
  const int32_t* offsets = nullptr;  // [tiles + 1] exclusive prefix sum of visited
  int64_t row0 = 0;                  // the first row (of the full layout) the records buffer holds
};

// Largest number of blend backward records (kBlendGrads values of value_bytes each) held at once:
// kRecordsBudgetMiB (core/constants.h) by default (chunks cost time: each adds kernel launches and
// a pass over the Gaussians), or `mib` when >= 0 (the GSW_BLEND_RECORDS_MIB setting; 0: no limit,
// returned as -1). At least one row.
inline int64_t blend_records_budget(int value_bytes, double mib = -1.0) {
  if (mib == 0.0) return -1;
  const double bytes = (mib > 0.0 ? mib : kRecordsBudgetMiB) * 1048576.0;
  const int64_t rows = static_cast<int64_t>(bytes / (double(kBlendGrads) * value_bytes));
  return rows > 0 ? rows : 1;
}

// The chunks [t0, t1) of whole tiles a backward's records come in: tile t holds rows
// row_offsets[t] .. row_offsets[t + 1] - 1 (an exclusive prefix sum over the tiles); a chunk holds
// at most budget_rows of them (< 0: one chunk), a tile with more is a chunk of its own. Returns
// the largest chunk's rows. Host code (both backends).
inline int64_t plan_record_chunks(const int32_t* row_offsets, int64_t tiles, int64_t budget_rows,
                                  std::vector<std::pair<int64_t, int64_t>>& chunks) {
  chunks.clear();
  int64_t max_rows = 0;
  for (int64_t t0 = 0; t0 < tiles;) {
    int64_t t1 = t0 + 1;
    while (t1 < tiles && (budget_rows < 0 || row_offsets[t1 + 1] - row_offsets[t0] <= budget_rows)) ++t1;
    chunks.emplace_back(t0, t1);
    max_rows = row_offsets[t1] - row_offsets[t0] > max_rows ? row_offsets[t1] - row_offsets[t0] : max_rows;
    t0 = t1;
  }
  return max_rows;
}

// The intersections (sorted positions [lo, hi)) whose records a reduction adds up; `accumulate`: onto
// the gradients already stored (a chunk after the first), else from zero.
struct SlotSpan {
  int32_t lo = 0, hi = INT32_MAX;
  bool accumulate = false;
};

// The last tile t in [lo, lo + span) (or [lo, tiles) if tile_offsets[lo + span] <= s) with
// tile_offsets[t] <= s, given tile_offsets[lo] <= s: the (non-empty) tile whose list range holds
// sorted position s. Branch-free bisection; tile_offsets[tiles] = M > s.
GSW_HD int32_t tile_of_slot(const int32_t* tile_offsets, int32_t tiles, int32_t lo, int32_t span, int32_t s) {
  int32_t n = tiles - lo;
  if (span < n && tile_offsets[lo + span] > s) n = span;
  while (n > 1) {
    const int32_t half = n >> 1;
    lo = tile_offsets[lo + half] <= s ? lo + half : lo;
    n -= half;
  }
  return lo;
}

// The record of sorted position s of a Gaussian's intersection (nullptr: s lies behind its tile's
// visited front, so no pixel blended it there). `t` is the tile of an earlier intersection of the
// same Gaussian (-1: none) and becomes s's: a Gaussian's intersections come in increasing tile
// order (binning emits its footprint row by row), so the search starts after it: the next tile
// (the same footprint row), else within the next two tile rows, else anywhere after.
template <typename T>
GSW_HD const T* blend_record(const TileBins& bins, const BlendRecords& layout, const T* records, int32_t s,
                             int32_t& t) {
  if (layout.visited == nullptr) return records + int64_t(kBlendGrads) * (s - layout.row0);
  const int32_t tiles = bins.tiles_x * bins.tiles_y;
  const int32_t* to = bins.tile_offsets;
  const int32_t next = t + 1;
  t = next + 1 < tiles && to[next + 1] <= s ? tile_of_slot(to, tiles, next + 1, t < 0 ? tiles : 2 * bins.tiles_x, s)
                                             : next;
  const int32_t pos = s - to[t];
  return pos < layout.visited[t] ? records + int64_t(kBlendGrads) * (layout.offsets[t] + pos - layout.row0) : nullptr;
}

// Gaussian i's blend cotangents, acc in record order (kBlendGrads values).
template <typename T>
GSW_HD void store_blend_grads(const RasterGradParams<T>& g, int64_t i, const T* acc) {
  g.v_means2d[2 * i] = acc[0];
  g.v_means2d[2 * i + 1] = acc[1];
  GSW_UNROLL
  for (int k = 0; k < 3; ++k) g.v_conics[3 * i + k] = acc[2 + k];
  g.v_opacities[i] = acc[5];
  GSW_UNROLL
  for (int k = 0; k < 3; ++k) g.v_colors[3 * i + k] = acc[6 + k];
  g.v_depths[i] = acc[9];
}

// Gaussian i's stored blend cotangents, in record order (kBlendGrads values).
template <typename T>
GSW_HD void load_blend_grads(const RasterGradParams<T>& g, int64_t i, T* acc) {
  acc[0] = g.v_means2d[2 * i];
  acc[1] = g.v_means2d[2 * i + 1];
  GSW_UNROLL
  for (int k = 0; k < 3; ++k) acc[2 + k] = g.v_conics[3 * i + k];
  acc[5] = g.v_opacities[i];
  GSW_UNROLL
  for (int k = 0; k < 3; ++k) acc[6 + k] = g.v_colors[3 * i + k];
  acc[9] = g.v_depths[i];
}

// Whether Gaussian i has an intersection in `span` (its sorted positions grow with e: binning emits
// a footprint's tiles in row-major order).
GSW_HD bool has_slots_in(const TileBins& bins, int64_t i, const SlotSpan& span) {
  const int32_t e0 = bins.entry_offsets[i], e1 = bins.entry_offsets[i + 1];
  return e0 < e1 && bins.entry_slots[e1 - 1] >= span.lo && bins.entry_slots[e0] < span.hi;
}

// Adds the records of Gaussian i's intersections e = entry_offsets[i] + first, + first + stride, ...
// whose sorted positions lie in `span` to acc, in that order (an intersection behind its tile's
// visited front has no record).
template <typename T>
GSW_HD void add_blend_records(const TileBins& bins, const BlendRecords& layout, const T* records, int64_t i,
                              const SlotSpan& span, int32_t first, int32_t stride, T* acc) {
  int32_t t = -1;
  for (int32_t e = bins.entry_offsets[i] + first; e < bins.entry_offsets[i + 1]; e += stride) {
    const int32_t s = bins.entry_slots[e];
    if (s < span.lo) continue;
    if (s >= span.hi) break;  // the positions grow with e
    const T* r = blend_record(bins, layout, records, s, t);
    if (r == nullptr) continue;
    GSW_UNROLL
    for (int k = 0; k < kBlendGrads; ++k) acc[k] += r[k];
  }
}

// Blend backward, second pass: Gaussian i's cotangents are the sum of its visited intersections'
// records (kBlendGrads values each, in kBlendGrads order), added in intersection order e =
// entry_offsets[i] .. entry_offsets[i + 1] - 1 from zero; an intersection behind its tile's visited
// front contributes nothing. A fixed order with no atomics: the gradients are the same bits on
// every run. (The CPU backend reduces every Gaussian so; CUDA those with few intersections, and the
// others with a warp each in another fixed order, see rasterize_cuda.cu.) A chunked backward adds
// each chunk's intersections (`span`) in the same order onto the stored sums, which gives the same
// bits as one pass; Gaussians with none in the span are left as they are.
template <typename T>
GSW_HD void reduce_blend_grads(const TileBins& bins, const BlendRecords& layout, const T* records,
                               const RasterGradParams<T>& g, int64_t i, const SlotSpan& span = SlotSpan{}) {
  T acc[kBlendGrads];
  if (span.accumulate) {
    if (!has_slots_in(bins, i, span)) return;
    load_blend_grads(g, i, acc);
  } else {
    GSW_UNROLL
    for (int k = 0; k < kBlendGrads; ++k) acc[k] = T(0);
  }
  add_blend_records(bins, layout, records, i, span, 0, 1, acc);
  store_blend_grads(g, i, acc);
}

// Per-Gaussian contribution of the blending weights w_i(p) = alpha_i(p) T_i(p) under a weight
// map: V[i, c] = sum_p weights[c, p] w_i(p); hits[i] = #pixels with w_i(p) > 0;
// max_weight[i] = max_p w_i(p).
template <typename T>
struct ContributionParams {
  int C = 0;
  const T* weights = nullptr;   // [C, H, W]
  T* contribution = nullptr;    // [N, C]
  int32_t* hits = nullptr;      // [N]
  T* max_weight = nullptr;      // [N]
};

}  // namespace gsw
