// CPU tile binning: each tile's Gaussians, front to back (depth, then index).
//
// Instead of sorting (tile, depth) keys of all M intersections, the visible Gaussians are
// sorted once by depth (LSD radix sort on the float bits for float32, a stable sort for
// float64) and then scattered into their tiles in that order (a counting sort by tile), which
// keeps every tile's list depth-ordered: O(N + M) for float32, the scatter in parallel.
#include <algorithm>
#include <cstring>
#include <vector>

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
void count_tiles(int N, const T* means2d, const int32_t* radii, int tiles_x, int tiles_y,
                 int32_t* tiles_touched) {
  parallel_items(N, [&](int64_t i) {
    int x0, y0, x1, y1;
    tiles_touched[i] = radii[i] > 0
                           ? tile_rect(Vec2<T>{means2d[2 * i], means2d[2 * i + 1]}, radii[i],
                                       tiles_x, tiles_y, x0, y0, x1, y1)
                           : 0;
  });
}

template <typename T>
void fill_bins(int N, const T* means2d, const int32_t* radii, const T* depths, int32_t* tile_offsets,
               int32_t* gauss_ids, const int32_t* entry_offsets, int32_t* entry_slots,
               int tiles_x, int tiles_y) {
  const int num_tiles = tiles_x * tiles_y;
  std::vector<int32_t> order;
  order.reserve(N);
  for (int i = 0; i < N; ++i)
    if (entry_offsets[i + 1] > entry_offsets[i]) order.push_back(i);
  sort_by_depth(depths, order);

  auto rect_of = [&](int32_t g, int& x0, int& y0, int& x1, int& y1) {
    tile_rect(Vec2<T>{means2d[2 * g], means2d[2 * g + 1]}, radii[g], tiles_x, tiles_y, x0, y0, x1,
              y1);
  };
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
      for (int64_t k = lo; k < hi; ++k) {
        int x0, y0, x1, y1;
        rect_of(order[k], x0, y0, x1, y1);
        for (int ty = y0; ty < y1; ++ty)
          for (int tx = x0; tx < x1; ++tx) ++cnt[ty * tiles_x + tx];
      }
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
        int x0, y0, x1, y1;
        rect_of(g, x0, y0, x1, y1);
        int32_t e = entry_offsets[g];
        for (int ty = y0; ty < y1; ++ty)
          for (int tx = x0; tx < x1; ++tx) {
            const int32_t slot = cursor[ty * tiles_x + tx]++;
            gauss_ids[slot] = g;
            entry_slots[e++] = slot;
          }
      }
    }
  });
}

template void count_tiles<float>(int, const float*, const int32_t*, int, int, int32_t*);
template void count_tiles<double>(int, const double*, const int32_t*, int, int, int32_t*);
template void fill_bins<float>(int, const float*, const int32_t*, const float*, int32_t*, int32_t*,
                               const int32_t*, int32_t*, int, int);
template void fill_bins<double>(int, const double*, const int32_t*, const double*, int32_t*,
                                int32_t*, const int32_t*, int32_t*, int, int);

}  // namespace gsw::cpu
