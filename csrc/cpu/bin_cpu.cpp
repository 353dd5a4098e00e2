// CPU tile binning: each tile's Gaussians, front to back (depth, then index).
//
// Each Gaussian's tiles are those of its tile_footprint (core/tiles.h), enumerated row-major.
// Instead of sorting (tile, depth) keys of all M intersections, the visible Gaussians are
// sorted once by depth (LSD radix sort on the float bits for float32, a stable sort for
// float64) and then scattered into their tiles in that order (a counting sort by tile), which
// keeps every tile's list depth-ordered: O(N + M) for float32, the scatter in parallel.
#include <algorithm>
#include <cstring>
#include <vector>

#include "core/tiles.h"
#include "cpu/backend_cpu.h"
#include "cpu/parallel.h"

namespace gsw::cpu {

namespace {

// Stable LSD radix sort of `ids` by non-negative float keys (bit patterns are monotonic).
void radix_sort_by_depth(const float* depths, std::vector<int32_t>& ids) {
  const size_t n = ids.size();
  std::vector<uint32_t> keys(n), keys_tmp(n);
  std::vector<int32_t> ids_tmp(n);
  for (size_t k = 0; k < n; ++k) std::memcpy(&keys[k], &depths[ids[k]], sizeof(uint32_t));
  for (int shift = 0; shift < 32; shift += 8) {
    size_t count[257] = {0};
    for (size_t k = 0; k < n; ++k) ++count[((keys[k] >> shift) & 0xFF) + 1];
    for (int b = 0; b < 256; ++b) count[b + 1] += count[b];
    for (size_t k = 0; k < n; ++k) {
      const size_t dst = count[(keys[k] >> shift) & 0xFF]++;
      keys_tmp[dst] = keys[k];
      ids_tmp[dst] = ids[k];
    }
    keys.swap(keys_tmp);
    ids.swap(ids_tmp);
  }
}

void sort_by_depth(const float* depths, std::vector<int32_t>& ids) {
  radix_sort_by_depth(depths, ids);
}
void sort_by_depth(const double* depths, std::vector<int32_t>& ids) {
  std::stable_sort(ids.begin(), ids.end(),
                   [depths](int32_t a, int32_t b) { return depths[a] < depths[b]; });
}

}  // namespace

template <typename T>
GSW_CPU_INLINE TileFootprint<T> footprint_of(const BinParams<T>& p, int64_t g) {
  return tile_footprint(Vec2<T>{p.means2d[2 * g], p.means2d[2 * g + 1]},
                        Sym2<T>{p.conics[3 * g], p.conics[3 * g + 1], p.conics[3 * g + 2]},
                        p.opacities[g], p.radii[g], p.tiles_x, p.tiles_y);
}

template <typename T>
void count_tiles(const BinParams<T>& p, int32_t* tiles_touched) {
  parallel_items(p.N, [&](int64_t i) { tiles_touched[i] = footprint_tiles(footprint_of(p, i)); });
}

// Calls fn(tile) for every tile of Gaussian g's footprint, row-major (the entry order).
template <typename T, typename F>
GSW_CPU_INLINE void for_each_tile(const BinParams<T>& p, int32_t g, F&& fn) {
  const TileFootprint<T> f = footprint_of(p, g);
  for (int ty = f.y0; ty < f.y1; ++ty) {
    int xa, xb;
    footprint_row(f, ty, xa, xb);
    for (int tx = xa; tx < xb; ++tx) fn(ty * p.tiles_x + tx);
  }
}

template <typename T>
void fill_bins(const BinParams<T>& p, int32_t* tile_offsets, int32_t* gauss_ids,
               const int32_t* entry_offsets, int32_t* entry_slots) {
  const int num_tiles = p.tiles_x * p.tiles_y;
  std::vector<int32_t> order;
  order.reserve(p.N);
  for (int i = 0; i < p.N; ++i)
    if (entry_offsets[i + 1] > entry_offsets[i]) order.push_back(i);
  sort_by_depth(p.depths, order);

  // Counting sort by tile in depth order, parallel over contiguous chunks of the depth order:
  // chunk c writes tile t's entries after those of chunks < c, so the result equals the
  // sequential scatter for any number of chunks.
  const int64_t V = static_cast<int64_t>(order.size());
  const int64_t chunks = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), V / 4096));
  std::vector<int32_t> counts(size_t(chunks) * num_tiles, 0);
  auto chunk_range = [&](int64_t c, int64_t& lo, int64_t& hi) {
    lo = V * c / chunks;
    hi = V * (c + 1) / chunks;
  };
  at::parallel_for(0, chunks, 1, [&](int64_t cb, int64_t ce) {
    for (int64_t c = cb; c < ce; ++c) {
      int64_t lo, hi;
      chunk_range(c, lo, hi);
      int32_t* cnt = counts.data() + size_t(c) * num_tiles;
      for (int64_t k = lo; k < hi; ++k) for_each_tile(p, order[k], [&](int t) { ++cnt[t]; });
    }
  });
  // tile_offsets, and each chunk's starting cursor per tile (counts become cursors).
  tile_offsets[0] = 0;
  for (int t = 0; t < num_tiles; ++t) {
    int32_t run = tile_offsets[t];
    for (int64_t c = 0; c < chunks; ++c) {
      const int32_t n = counts[size_t(c) * num_tiles + t];
      counts[size_t(c) * num_tiles + t] = run;
      run += n;
    }
    tile_offsets[t + 1] = run;
  }
  at::parallel_for(0, chunks, 1, [&](int64_t cb, int64_t ce) {
    for (int64_t c = cb; c < ce; ++c) {
      int64_t lo, hi;
      chunk_range(c, lo, hi);
      int32_t* cursor = counts.data() + size_t(c) * num_tiles;
      for (int64_t k = lo; k < hi; ++k) {
        const int32_t g = order[k];
        int32_t e = entry_offsets[g];
        for_each_tile(p, g, [&](int t) {
          const int32_t slot = cursor[t]++;
          gauss_ids[slot] = g;
          entry_slots[e++] = slot;
        });
      }
    }
  });
}

template void count_tiles<float>(const BinParams<float>&, int32_t*);
template void count_tiles<double>(const BinParams<double>&, int32_t*);
template void fill_bins<float>(const BinParams<float>&, int32_t*, int32_t*, const int32_t*, int32_t*);
template void fill_bins<double>(const BinParams<double>&, int32_t*, int32_t*, const int32_t*, int32_t*);

}  // namespace gsw::cpu
