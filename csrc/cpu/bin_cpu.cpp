// CPU tile binning: each tile's Gaussians, front to back (depth, then index).
//
// Each Gaussian's tiles are those of its tile_footprint (core/tiles.h), enumerated row-major
// once, by count_tiles.
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

// Static chunks of the Gaussians for the counting pass: [N c / n, N (c + 1) / n).
int64_t count_chunks(int64_t N) {
  return std::max<int64_t>(1, std::min<int64_t>(4 * at::get_num_threads(), N / 2048));
}

// Tile lists of Gaussians [g0, g1) into `out`. A tile kernel (cpu/parallel.h) so that the
// footprint's floor / ceil / sqrt compile to single instructions in the x86-64-v3 clone (the
// baseline x86-64 has no rounding instruction); no FMA contraction in this file, so both clones
// take the same decisions.
template <typename T>
GSW_CPU_KERNEL void count_range(const BinParams<T>& p, int64_t g0, int64_t g1, int32_t* tiles_touched,
                                std::vector<int32_t>& out) {
  for (int64_t g = g0; g < g1; ++g) {
    const TileFootprint<T> f = tile_footprint(
        Vec2<T>{p.means2d[2 * g], p.means2d[2 * g + 1]},
        Sym2<T>{p.conics[3 * g], p.conics[3 * g + 1], p.conics[3 * g + 2]}, p.opacities[g],
        p.radii[g], p.tiles_x, p.tiles_y);
    const size_t before = out.size();
    for (int ty = f.y0; ty < f.y1; ++ty) {
      int xa, xb;
      footprint_row(f, ty, xa, xb);
      for (int tx = xa; tx < xb; ++tx) out.push_back(ty * p.tiles_x + tx);
    }
    tiles_touched[g] = static_cast<int32_t>(out.size() - before);
  }
}

// The passes over the Gaussians in depth order read their entries in random order (cache misses):
// at position k they prefetch the entry offsets of position k + 16 and the entries of k + 8.
inline void prefetch_entries(const std::vector<int32_t>& order, const int32_t* entry_offsets,
                             const int32_t* entry_slots, int64_t k, int64_t hi) {
  constexpr int64_t kFar = 16, kNear = 8;
  if (k + kFar < hi) __builtin_prefetch(entry_offsets + order[k + kFar]);
  if (k + kNear < hi) __builtin_prefetch(entry_slots + entry_offsets[order[k + kNear]]);
}

}  // namespace

template <typename T>
void count_tiles(const BinParams<T>& p, int32_t* tiles_touched, TileLists& lists) {
  const int64_t n = count_chunks(p.N);
  lists.chunks.assign(size_t(n), {});
  at::parallel_for(0, n, 1, [&](int64_t cb, int64_t ce) {
    for (int64_t c = cb; c < ce; ++c)
      count_range(p, p.N * c / n, p.N * (c + 1) / n, tiles_touched, lists.chunks[size_t(c)]);
  });
}

template <typename T>
void fill_bins(const BinParams<T>& p, TileLists& lists, int32_t* tile_offsets, int32_t* gauss_ids,
               const int32_t* entry_offsets, int32_t* entry_slots) {
  const int num_tiles = p.tiles_x * p.tiles_y;
  // entry_slots[e] holds the tile of entry e until the scatter below replaces it by its slot.
  const int64_t n = static_cast<int64_t>(lists.chunks.size());
  at::parallel_for(0, n, 1, [&](int64_t cb, int64_t ce) {
    for (int64_t c = cb; c < ce; ++c) {
      const std::vector<int32_t>& tiles = lists.chunks[size_t(c)];
      if (!tiles.empty())
        std::memcpy(entry_slots + entry_offsets[p.N * c / n], tiles.data(), tiles.size() * sizeof(int32_t));
    }
  });
  lists.chunks.clear();
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
      for (int64_t k = lo; k < hi; ++k) {
        prefetch_entries(order, entry_offsets, entry_slots, k, hi);
        const int32_t g = order[k];
        for (int32_t e = entry_offsets[g]; e < entry_offsets[g + 1]; ++e) ++cnt[entry_slots[e]];
      }
    }
  });
  // tile_offsets, and each chunk's starting cursor per tile (counts become cursors).
  tile_offsets[0] = 0;
  for (int t = 0; t < num_tiles; ++t) {
    int32_t run = tile_offsets[t];
    for (int64_t c = 0; c < chunks; ++c) {
      const int32_t cn = counts[size_t(c) * num_tiles + t];
      counts[size_t(c) * num_tiles + t] = run;
      run += cn;
    }
    tile_offsets[t + 1] = run;
  }
  at::parallel_for(0, chunks, 1, [&](int64_t cb, int64_t ce) {
    for (int64_t c = cb; c < ce; ++c) {
      int64_t lo, hi;
      chunk_range(c, lo, hi);
      int32_t* cursor = counts.data() + size_t(c) * num_tiles;
      for (int64_t k = lo; k < hi; ++k) {
        prefetch_entries(order, entry_offsets, entry_slots, k, hi);
        const int32_t g = order[k];
        for (int32_t e = entry_offsets[g]; e < entry_offsets[g + 1]; ++e) {
          const int32_t slot = cursor[entry_slots[e]]++;
          gauss_ids[slot] = g;
          entry_slots[e] = slot;
        }
      }
    }
  });
}

template void count_tiles<float>(const BinParams<float>&, int32_t*, TileLists&);
template void count_tiles<double>(const BinParams<double>&, int32_t*, TileLists&);
template void fill_bins<float>(const BinParams<float>&, TileLists&, int32_t*, int32_t*, const int32_t*, int32_t*);
template void fill_bins<double>(const BinParams<double>&, TileLists&, int32_t*, int32_t*, const int32_t*,
                                int32_t*);

}  // namespace gsw::cpu
