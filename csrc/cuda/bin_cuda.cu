// CUDA tile binning: each tile's Gaussians, front to back (depth, then index), as on the CPU.
//
// Two stable cub radix sorts, as the CPU's depth sort + counting sort by tile: the Gaussians are
// sorted once by depth (N keys: the float bit pattern, which orders like the value since depths
// are > NEAR_PLANE > 0 or exactly 0 for culled ones; 64-bit patterns for float64), their
// intersections (the tiles of tile_footprint, core/tiles.h) are emitted in that order, and the M
// (tile id, entry index) pairs are sorted by
// the tile id alone (log2(tiles) bits: 2 passes of 32-bit keys at 1080p, instead of 6 passes of
// 64-bit (tile << 32 | depth) keys). Both sorts are stable, so each tile's list is in depth
// order and equal depths keep the index order: the same bins as the CPU, bit for bit.
#include <cub/device/device_radix_sort.cuh>
#include <algorithm>
#include <type_traits>

#include "core/tiles.h"
#include "cuda/common.cuh"

namespace gsw::cuda {

namespace {

constexpr int kThreads = 256;

template <typename T>
__device__ __forceinline__ TileFootprint<T> footprint_of(const BinParams<T>& p, int g) {
  return tile_footprint(Vec2<T>{p.means2d[2 * g], p.means2d[2 * g + 1]},
                        Sym2<T>{p.conics[3 * g], p.conics[3 * g + 1], p.conics[3 * g + 2]},
                        p.opacities[g], p.radii[g], p.tiles_x, p.tiles_y);
}

template <typename T>
__global__ void count_tiles_kernel(BinParams<T> p, int32_t* __restrict__ touched) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= p.N) return;
  touched[i] = footprint_tiles(footprint_of(p, i));
}

// Depth sort keys: the bit pattern (non-negative values order like their patterns).
__device__ __forceinline__ uint32_t depth_bits(float d) { return __float_as_uint(d); }
__device__ __forceinline__ uint64_t depth_bits(double d) { return static_cast<uint64_t>(__double_as_longlong(d)); }

template <typename T, typename K>
__global__ void depth_keys_kernel(int N, const T* __restrict__ depths, K* __restrict__ keys,
                                  int32_t* __restrict__ ids) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= N) return;
  keys[i] = depth_bits(depths[i]);
  ids[i] = i;
}

// Intersection counts in depth order (for the scan that places each Gaussian's emitted entries).
__global__ void counts_in_order_kernel(int N, const int32_t* __restrict__ order,
                                       const int32_t* __restrict__ entry_offsets,
                                       int32_t* __restrict__ counts) {
  const int j = blockIdx.x * blockDim.x + threadIdx.x;
  if (j >= N) return;
  const int g = order[j];
  counts[j] = entry_offsets[g + 1] - entry_offsets[g];
}

// Where each Gaussian's entries go in depth order, by Gaussian: emit_at[order[j]] = emit_offsets[j].
__global__ void emit_at_kernel(int N, const int32_t* __restrict__ order, const int32_t* __restrict__ emit_offsets,
                               int32_t* __restrict__ emit_at) {
  const int j = blockIdx.x * blockDim.x + threadIdx.x;
  if (j >= N) return;
  emit_at[order[j]] = emit_offsets[j];
}

// Gaussian g emits its intersections at emit_at[g] (their place in depth order): its tile ids
// (row-major over its footprint, the CPU's entry order) as keys and its entry indices e as values;
// entry_slots[e] temporarily holds g (see slots_kernel). Thread g reads Gaussian g's parameters
// (coalesced; in depth order they would be gathers). A warp of small footprints (at most
// kEmitSerial tiles each) lets each thread emit its own. Otherwise the warp shares the work: it
// walks its 32 Gaussians' footprint rows together, 32 rows at a time (lane l: the row's chord,
// footprint_row), and then those rows' entries 32 at a time, lane l the l-th entry: every lane busy
// whatever the footprints' sizes (one splat of hundreds of tiles among small ones, or all large),
// and the stores of one footprint coalesced. The outputs are the same either way.
constexpr int kEmitSerial = 8;

// Warp-inclusive prefix sum.
__device__ __forceinline__ int warp_inclusive_sum(int v, int lane) {
#pragma unroll
  for (int o = 1; o < 32; o <<= 1) {
    const int u = __shfl_up_sync(kFullMask, v, o);
    if (lane >= o) v += u;
  }
  return v;
}

// Number of the 32 non-decreasing values ends[0..31] that are <= v (ends[31] > v): the index of the
// first one above v.
__device__ __forceinline__ int first_above(const int32_t* ends, int v) {
  int i = 0;
#pragma unroll
  for (int step = 16; step > 0; step >>= 1)
    if (ends[i + step - 1] <= v) i += step;
  return i;
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    emit_keys_kernel(BinParams<T> p, const int32_t* __restrict__ emit_at, const int32_t* __restrict__ entry_offsets,
                     uint32_t* __restrict__ keys, int32_t* __restrict__ vals, int32_t* __restrict__ entry_slots) {
  // Per thread: its Gaussian's footprint, first entry, first output, and the warp's running totals
  // of entries before it and of footprint rows up to it; per row of the current 32: the warp's
  // running total of entries, its Gaussian (thread) and tile row, and its first tile column.
  __shared__ TileFootprint<T> s_foot[kThreads];
  __shared__ int32_t s_e0[kThreads], s_k0[kThreads], s_q0[kThreads], s_rows_end[kThreads];
  __shared__ int32_t s_row_end[kThreads], s_row_lane[kThreads], s_row_ty[kThreads], s_row_xa[kThreads];
  const int g = blockIdx.x * blockDim.x + threadIdx.x;
  const int lane = static_cast<int>(threadIdx.x & 31), warp0 = static_cast<int>(threadIdx.x & ~31u);
  int32_t e0 = 0, count = 0, k0 = 0;
  if (g < p.N) {  // no early return: the warp's lanes all take part in the shuffles below
    e0 = entry_offsets[g];
    count = entry_offsets[g + 1] - e0;
    k0 = emit_at[g];
  }
  TileFootprint<T> f{};
  if (count > 0) f = footprint_of(p, g);
  if (__reduce_max_sync(kFullMask, static_cast<unsigned>(count)) <= unsigned(kEmitSerial)) {
    if (count == 0) return;
    int32_t k = k0, e = e0;
    for (int ty = f.y0; ty < f.y1; ++ty) {
      int xa, xb;
      footprint_row(f, ty, xa, xb);
      for (int tx = xa; tx < xb; ++tx) {
        keys[k] = static_cast<uint32_t>(ty * p.tiles_x + tx);
        vals[k] = e;
        entry_slots[e] = g;
        ++k;
        ++e;
      }
    }
    return;
  }
  const int rows_end = warp_inclusive_sum(count > 0 ? f.y1 - f.y0 : 0, lane);
  const int total_rows = __shfl_sync(kFullMask, rows_end, 31);
  s_foot[threadIdx.x] = f;
  s_e0[threadIdx.x] = e0;
  s_k0[threadIdx.x] = k0;
  s_q0[threadIdx.x] = warp_inclusive_sum(count, lane) - count;
  s_rows_end[threadIdx.x] = rows_end;
  __syncwarp();
  int32_t emitted = 0;  // the warp's entries of the previous rows
  for (int r0 = 0; r0 < total_rows; r0 += 32) {
    const int r = r0 + lane;
    int src = 0, ty = 0, xa = 0, xb = 0;
    if (r < total_rows) {
      src = first_above(s_rows_end + warp0, r);
      const TileFootprint<T> fs = s_foot[warp0 + src];
      ty = fs.y1 - (s_rows_end[warp0 + src] - r);
      footprint_row(fs, ty, xa, xb);
    }
    const int row_end = warp_inclusive_sum(xb - xa, lane);
    const int n_entries = __shfl_sync(kFullMask, row_end, 31);
    __syncwarp();  // the previous rows' entries are all emitted
    s_row_end[threadIdx.x] = row_end;
    s_row_lane[threadIdx.x] = warp0 + src;
    s_row_ty[threadIdx.x] = ty;
    s_row_xa[threadIdx.x] = xa;
    __syncwarp();
    for (int q = lane; q < n_entries; q += 32) {
      const int row = first_above(s_row_end + warp0, q);
      const int q_row = row == 0 ? 0 : s_row_end[warp0 + row - 1];
      const int sl = s_row_lane[warp0 + row];
      const int32_t local = emitted + q - s_q0[sl];  // entry index within its Gaussian's list
      const int32_t k = s_k0[sl] + local, e = s_e0[sl] + local;
      keys[k] = static_cast<uint32_t>(s_row_ty[warp0 + row] * p.tiles_x + s_row_xa[warp0 + row] + (q - q_row));
      vals[k] = e;
      entry_slots[e] = sl - warp0 + (g - lane);
    }
    emitted += n_entries;
  }
}

// tile_offsets[t] = first sorted position of tile t (M for empty trailing tiles).
__global__ void tile_offsets_kernel(int64_t M, int num_tiles, const uint32_t* __restrict__ keys,
                                    int32_t* __restrict__ tile_offsets) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= M) return;
  const int t = static_cast<int>(keys[i]);
  const int prev = i == 0 ? -1 : static_cast<int>(keys[i - 1]);
  for (int k = prev + 1; k <= t; ++k) tile_offsets[k] = static_cast<int32_t>(i);
  if (i == M - 1)
    for (int k = t + 1; k <= num_tiles; ++k) tile_offsets[k] = static_cast<int32_t>(M);
}

// Sorted position i holds entry e = sorted_entries[i] of Gaussian g = entry_slots[e] (written by
// emit_keys_kernel): gauss_ids[i] = g and entry_slots[e] = i, as on the CPU. Each thread reads and
// writes only its own i and e (sorted_entries may alias gauss_ids).
__global__ void slots_kernel(int64_t M, const int32_t* sorted_entries, int32_t* gauss_ids,
                             int32_t* __restrict__ entry_slots) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= M) return;
  const int32_t e = sorted_entries[i];
  const int32_t g = entry_slots[e];
  gauss_ids[i] = g;
  entry_slots[e] = static_cast<int32_t>(i);
}

int bits_for(int64_t n) {  // number of bits to represent values in [0, n]
  int b = 0;
  while ((int64_t(1) << b) <= n) ++b;
  return b;
}

// cub radix sort of (key, value) pairs in double buffers; returns which buffer holds the result.
template <typename K, typename V>
int radix_sort_pairs(K* keys0, K* keys1, V* vals0, V* vals1, int64_t n, int begin_bit,
                     int end_bit, cudaStream_t stream) {
  cub::DoubleBuffer<K> kb(keys0, keys1);
  cub::DoubleBuffer<V> vb(vals0, vals1);
  size_t temp_bytes = 0;
  GSW_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(nullptr, temp_bytes, kb, vb, static_cast<int>(n), begin_bit,
                                                 end_bit, stream));
  DeviceBuffer temp(temp_bytes);
  GSW_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(temp.as<void>(), temp_bytes, kb, vb, static_cast<int>(n),
                                                 begin_bit, end_bit, stream));
  return kb.selector;
}

}  // namespace

template <typename T>
void count_tiles(const BinParams<T>& p, int32_t* tiles_touched) {
  if (p.N <= 0) return;
  count_tiles_kernel<T><<<blocks_for(p.N, kThreads), kThreads, 0, current_stream()>>>(p, tiles_touched);
  GSW_KERNEL_CHECK();
}

template <typename T>
void fill_bins(const BinParams<T>& p, int32_t* tile_offsets, int32_t* gauss_ids,
               const int32_t* entry_offsets, int32_t* entry_slots, int64_t M) {
  cudaStream_t stream = current_stream();
  const int N = p.N;
  const int num_tiles = p.tiles_x * p.tiles_y;
  if (M <= 0 || N <= 0) {
    GSW_CUDA_CHECK(
        cudaMemsetAsync(tile_offsets, 0, sizeof(int32_t) * (num_tiles + 1), stream));
    return;
  }
  // 1. Depth order of the Gaussians (stable: equal depths keep the index order).
  using DepthKey = typename std::conditional<std::is_same<T, double>::value, uint64_t, uint32_t>::type;
  DeviceBuffer dkeys(sizeof(DepthKey) * 2 * N), ids(sizeof(int32_t) * 2 * N);
  DepthKey* dk = dkeys.as<DepthKey>();
  int32_t* id = ids.as<int32_t>();
  depth_keys_kernel<T, DepthKey><<<blocks_for(N, kThreads), kThreads, 0, stream>>>(N, p.depths, dk, id);
  GSW_KERNEL_CHECK();
  const int sel = radix_sort_pairs(dk, dk + N, id, id + N, N, 0, int(8 * sizeof(DepthKey)), stream);
  const int32_t* order = sel ? id + N : id;
  // 2. Where each Gaussian's entries go in depth order: exclusive scan of its counts, then by Gaussian.
  DeviceBuffer counts_buf(sizeof(int32_t) * 2 * N);
  int32_t* counts = counts_buf.as<int32_t>();
  int32_t* emit_offsets = counts + N;
  int32_t* emit_at = counts;  // once the scan has read the counts
  counts_in_order_kernel<<<blocks_for(N, kThreads), kThreads, 0, stream>>>(N, order, entry_offsets, counts);
  GSW_KERNEL_CHECK();
  exclusive_sum(counts, emit_offsets, N, stream);
  emit_at_kernel<<<blocks_for(N, kThreads), kThreads, 0, stream>>>(N, order, emit_offsets, emit_at);
  GSW_KERNEL_CHECK();
  // 3. (tile, entry) pairs in depth order, then a stable sort by tile.
  DeviceBuffer keys(sizeof(uint32_t) * 2 * M), vals_alt(sizeof(int32_t) * M);
  uint32_t* k0 = keys.as<uint32_t>();
  int32_t* v1 = vals_alt.as<int32_t>();
  emit_keys_kernel<T><<<blocks_for(N, kThreads), kThreads, 0, stream>>>(p, emit_at, entry_offsets, k0, gauss_ids,
                                                                         entry_slots);
  GSW_KERNEL_CHECK();
  const int tile_sel = radix_sort_pairs(k0, k0 + M, gauss_ids, v1, M, 0, std::max(1, bits_for(num_tiles - 1)), stream);
  const uint32_t* sorted_keys = tile_sel ? k0 + M : k0;
  tile_offsets_kernel<<<blocks_for(M, kThreads), kThreads, 0, stream>>>(M, num_tiles, sorted_keys, tile_offsets);
  GSW_KERNEL_CHECK();
  // 4. gauss_ids and entry_slots from the sorted entries.
  slots_kernel<<<blocks_for(M, kThreads), kThreads, 0, stream>>>(M, tile_sel ? v1 : gauss_ids, gauss_ids,
                                                                 entry_slots);
  GSW_KERNEL_CHECK();
}

template void count_tiles<float>(const BinParams<float>&, int32_t*);
template void count_tiles<double>(const BinParams<double>&, int32_t*);
template void fill_bins<float>(const BinParams<float>&, int32_t*, int32_t*, const int32_t*, int32_t*, int64_t);
template void fill_bins<double>(const BinParams<double>&, int32_t*, int32_t*, const int32_t*, int32_t*, int64_t);

}  // namespace gsw::cuda
