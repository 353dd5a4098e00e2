// CUDA tile binning: each tile's Gaussians, front to back (depth, then index), as on the CPU.
//
// Two stable cub radix sorts, as the CPU's depth sort + counting sort by tile: the Gaussians are
// sorted once by depth (N keys: the float bit pattern, which orders like the value since depths
// are > NEAR_PLANE > 0 or exactly 0 for culled ones; 64-bit patterns for float64), their
// intersections are emitted in that order, and the M (tile id, Gaussian id) pairs are sorted by
// the tile id alone (log2(tiles) bits: 2 passes of 32-bit keys at 1080p, instead of 6 passes of
// 64-bit (tile << 32 | depth) keys). Both sorts are stable, so each tile's list is in depth
// order and equal depths keep the index order: the same bins as the CPU, bit for bit.
#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_scan.cuh>
#include <algorithm>
#include <type_traits>

#include "cuda/common.cuh"

namespace gsw::cuda {

namespace {

constexpr int kThreads = 256;

template <typename T>
__global__ void count_tiles_kernel(int N, const T* __restrict__ means2d,
                                   const int32_t* __restrict__ radii, int tiles_x, int tiles_y,
                                   int32_t* __restrict__ touched) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= N) return;
  int x0, y0, x1, y1;
  touched[i] = radii[i] > 0 ? tile_rect(Vec2<T>{means2d[2 * i], means2d[2 * i + 1]}, radii[i],
                                        tiles_x, tiles_y, x0, y0, x1, y1)
                            : 0;
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

// Thread j emits the intersections of the j-th Gaussian in depth order: its tile ids (row-major
// over its tile rectangle) at emit_offsets[j].
template <typename T>
__global__ void emit_keys_kernel(int N, const int32_t* __restrict__ order, const int32_t* __restrict__ emit_offsets,
                                 const T* __restrict__ means2d, const int32_t* __restrict__ radii, int tiles_x,
                                 int tiles_y, uint32_t* __restrict__ keys, int32_t* __restrict__ vals) {
  const int j = blockIdx.x * blockDim.x + threadIdx.x;
  if (j >= N) return;
  const int g = order[j];
  if (radii[g] <= 0) return;
  int x0, y0, x1, y1;
  if (tile_rect(Vec2<T>{means2d[2 * g], means2d[2 * g + 1]}, radii[g], tiles_x, tiles_y, x0, y0, x1, y1) == 0) return;
  int32_t e = emit_offsets[j];
  for (int ty = y0; ty < y1; ++ty)
    for (int tx = x0; tx < x1; ++tx) {
      keys[e] = static_cast<uint32_t>(ty * tiles_x + tx);
      vals[e] = g;
      ++e;
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

// entry_slots[e] = sorted position of intersection e (e enumerates a Gaussian's tiles
// row-major), as on the CPU.
template <typename T>
__global__ void entry_slots_kernel(int64_t M, const T* __restrict__ means2d,
                                   const int32_t* __restrict__ radii,
                                   const int32_t* __restrict__ entry_offsets,
                                   const uint32_t* __restrict__ keys,
                                   const int32_t* __restrict__ gauss_ids, int tiles_x,
                                   int tiles_y, int32_t* __restrict__ entry_slots) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= M) return;
  const int g = gauss_ids[i];
  const int t = static_cast<int>(keys[i]);
  int x0, y0, x1, y1;
  tile_rect(Vec2<T>{means2d[2 * g], means2d[2 * g + 1]}, radii[g], tiles_x, tiles_y, x0, y0, x1,
            y1);
  const int tx = t % tiles_x, ty = t / tiles_x;
  entry_slots[entry_offsets[g] + (ty - y0) * (x1 - x0) + (tx - x0)] = static_cast<int32_t>(i);
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
void count_tiles(int N, const T* means2d, const int32_t* radii, int tiles_x, int tiles_y,
                 int32_t* tiles_touched) {
  if (N <= 0) return;
  count_tiles_kernel<T><<<blocks_for(N, kThreads), kThreads, 0, current_stream()>>>(
      N, means2d, radii, tiles_x, tiles_y, tiles_touched);
  GSW_KERNEL_CHECK();
}

template <typename T>
void fill_bins(int N, const T* means2d, const int32_t* radii, const T* depths,
               int32_t* tile_offsets, int32_t* gauss_ids, const int32_t* entry_offsets,
               int32_t* entry_slots, int tiles_x, int tiles_y, int64_t M) {
  cudaStream_t stream = current_stream();
  const int num_tiles = tiles_x * tiles_y;
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
  depth_keys_kernel<T, DepthKey><<<blocks_for(N, kThreads), kThreads, 0, stream>>>(N, depths, dk, id);
  GSW_KERNEL_CHECK();
  const int sel = radix_sort_pairs(dk, dk + N, id, id + N, N, 0, int(8 * sizeof(DepthKey)), stream);
  const int32_t* order = sel ? id + N : id;
  // 2. Where each Gaussian's entries go in depth order: exclusive scan of its counts.
  DeviceBuffer counts_buf(sizeof(int32_t) * 2 * N);
  int32_t* counts = counts_buf.as<int32_t>();
  int32_t* emit_offsets = counts + N;
  counts_in_order_kernel<<<blocks_for(N, kThreads), kThreads, 0, stream>>>(N, order, entry_offsets, counts);
  GSW_KERNEL_CHECK();
  size_t scan_bytes = 0;
  GSW_CUDA_CHECK(cub::DeviceScan::ExclusiveSum(nullptr, scan_bytes, counts, emit_offsets, N, stream));
  {
    DeviceBuffer temp(scan_bytes);
    GSW_CUDA_CHECK(cub::DeviceScan::ExclusiveSum(temp.as<void>(), scan_bytes, counts, emit_offsets, N, stream));
  }
  // 3. (tile, Gaussian) pairs in depth order, then a stable sort by tile.
  DeviceBuffer keys(sizeof(uint32_t) * 2 * M), vals_alt(sizeof(int32_t) * M);
  uint32_t* k0 = keys.as<uint32_t>();
  int32_t* v1 = vals_alt.as<int32_t>();
  emit_keys_kernel<T><<<blocks_for(N, kThreads), kThreads, 0, stream>>>(N, order, emit_offsets, means2d, radii,
                                                                         tiles_x, tiles_y, k0, gauss_ids);
  GSW_KERNEL_CHECK();
  const int tile_sel = radix_sort_pairs(k0, k0 + M, gauss_ids, v1, M, 0, std::max(1, bits_for(num_tiles - 1)), stream);
  if (tile_sel)
    GSW_CUDA_CHECK(cudaMemcpyAsync(gauss_ids, v1, sizeof(int32_t) * M, cudaMemcpyDeviceToDevice, stream));
  const uint32_t* sorted_keys = tile_sel ? k0 + M : k0;
  tile_offsets_kernel<<<blocks_for(M, kThreads), kThreads, 0, stream>>>(M, num_tiles, sorted_keys, tile_offsets);
  GSW_KERNEL_CHECK();
  entry_slots_kernel<T><<<blocks_for(M, kThreads), kThreads, 0, stream>>>(
      M, means2d, radii, entry_offsets, sorted_keys, gauss_ids, tiles_x, tiles_y, entry_slots);
  GSW_KERNEL_CHECK();
}

template void count_tiles<float>(int, const float*, const int32_t*, int, int, int32_t*);
template void count_tiles<double>(int, const double*, const int32_t*, int, int, int32_t*);
template void fill_bins<float>(int, const float*, const int32_t*, const float*, int32_t*,
                               int32_t*, const int32_t*, int32_t*, int, int, int64_t);
template void fill_bins<double>(int, const double*, const int32_t*, const double*, int32_t*,
                                int32_t*, const int32_t*, int32_t*, int, int, int64_t);

}  // namespace gsw::cuda
