// CUDA tile binning: each tile's Gaussians, front to back (depth, then index), as on the CPU.
//
// Every (Gaussian, tile) intersection gets a 64-bit key (tile << 32 | depth key) and the pairs
// (key, Gaussian id) are sorted with cub::DeviceRadixSort over the bits in use. The sort is
// stable and the pairs are generated in Gaussian order, so equal depths keep the index order.
//  * float32: the depth key is the float's bit pattern (depths are > NEAR_PLANE > 0, so bit
//    patterns order like the values);
//  * float64: the depth key is the Gaussian's rank in a stable sort of the double bit patterns
//    (exactly the CPU's std::stable_sort order).
#include <cub/device/device_radix_sort.cuh>

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

__device__ __forceinline__ uint32_t depth_key(const float* depths, const uint32_t*, int g) {
  return __float_as_uint(depths[g]);
}
__device__ __forceinline__ uint32_t depth_key(const double*, const uint32_t* rank, int g) {
  return rank[g];
}

// One thread per Gaussian writes its intersections' keys, row-major over its tile rectangle
// (the CPU's entry order).
template <typename T>
__global__ void emit_keys_kernel(int N, const T* __restrict__ means2d,
                                 const int32_t* __restrict__ radii, const T* __restrict__ depths,
                                 const uint32_t* __restrict__ rank,
                                 const int32_t* __restrict__ entry_offsets, int tiles_x,
                                 int tiles_y, uint64_t* __restrict__ keys,
                                 int32_t* __restrict__ vals) {
  const int g = blockIdx.x * blockDim.x + threadIdx.x;
  if (g >= N) return;
  int32_t e = entry_offsets[g];
  if (entry_offsets[g + 1] == e) return;
  int x0, y0, x1, y1;
  tile_rect(Vec2<T>{means2d[2 * g], means2d[2 * g + 1]}, radii[g], tiles_x, tiles_y, x0, y0, x1,
            y1);
  const uint64_t dk = depth_key(depths, rank, g);
  for (int ty = y0; ty < y1; ++ty)
    for (int tx = x0; tx < x1; ++tx) {
      keys[e] = (uint64_t(ty * tiles_x + tx) << 32) | dk;
      vals[e] = g;
      ++e;
    }
}

// tile_offsets[t] = first sorted position of tile t (M for empty trailing tiles).
__global__ void tile_offsets_kernel(int64_t M, int num_tiles, const uint64_t* __restrict__ keys,
                                    int32_t* __restrict__ tile_offsets) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= M) return;
  const int t = static_cast<int>(keys[i] >> 32);
  const int prev = i == 0 ? -1 : static_cast<int>(keys[i - 1] >> 32);
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
                                   const uint64_t* __restrict__ keys,
                                   const int32_t* __restrict__ gauss_ids, int tiles_x,
                                   int tiles_y, int32_t* __restrict__ entry_slots) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= M) return;
  const int g = gauss_ids[i];
  const int t = static_cast<int>(keys[i] >> 32);
  int x0, y0, x1, y1;
  tile_rect(Vec2<T>{means2d[2 * g], means2d[2 * g + 1]}, radii[g], tiles_x, tiles_y, x0, y0, x1,
            y1);
  const int tx = t % tiles_x, ty = t / tiles_x;
  entry_slots[entry_offsets[g] + (ty - y0) * (x1 - x0) + (tx - x0)] = static_cast<int32_t>(i);
}

// float64 depth ranks: stable sort of (bits(depth), index) over all Gaussians.
__global__ void depth_bits_kernel(int N, const double* __restrict__ depths,
                                  uint64_t* __restrict__ bits, uint32_t* __restrict__ ids) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= N) return;
  bits[i] = static_cast<uint64_t>(__double_as_longlong(depths[i]));
  ids[i] = static_cast<uint32_t>(i);
}
__global__ void scatter_rank_kernel(int N, const uint32_t* __restrict__ sorted_ids,
                                    uint32_t* __restrict__ rank) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= N) return;
  rank[sorted_ids[i]] = static_cast<uint32_t>(i);
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
  // float64: depth ranks first.
  DeviceBuffer rank_buf(std::is_same<T, double>::value ? sizeof(uint32_t) * N : 0);
  if constexpr (std::is_same<T, double>::value) {
    DeviceBuffer bits(sizeof(uint64_t) * 2 * N), ids(sizeof(uint32_t) * 2 * N);
    uint64_t* b = bits.as<uint64_t>();
    uint32_t* id = ids.as<uint32_t>();
    depth_bits_kernel<<<blocks_for(N, kThreads), kThreads, 0, stream>>>(N, depths, b, id);
    GSW_KERNEL_CHECK();
    const int sel = radix_sort_pairs(b, b + N, id, id + N, N, 0, 64, stream);
    scatter_rank_kernel<<<blocks_for(N, kThreads), kThreads, 0, stream>>>(
        N, sel ? id + N : id, rank_buf.as<uint32_t>());
    GSW_KERNEL_CHECK();
  }
  DeviceBuffer keys(sizeof(uint64_t) * 2 * M), vals_alt(sizeof(int32_t) * M);
  uint64_t* k0 = keys.as<uint64_t>();
  uint64_t* k1 = k0 + M;
  int32_t* v1 = vals_alt.as<int32_t>();
  // Keys are written to k0 and values to v1 (the alternate value buffer), so that the common
  // case of an even number of sort passes ends in gauss_ids without a copy.
  emit_keys_kernel<T><<<blocks_for(N, kThreads), kThreads, 0, stream>>>(
      N, means2d, radii, depths, rank_buf.as<uint32_t>(), entry_offsets, tiles_x, tiles_y, k0,
      v1);
  GSW_KERNEL_CHECK();
  const int end_bit = 32 + bits_for(num_tiles - 1);
  cub::DoubleBuffer<uint64_t> kb(k0, k1);
  cub::DoubleBuffer<int32_t> vb(v1, gauss_ids);
  size_t temp_bytes = 0;
  GSW_CUDA_CHECK(
      cub::DeviceRadixSort::SortPairs(nullptr, temp_bytes, kb, vb, static_cast<int>(M), 0, end_bit, stream));
  {
    DeviceBuffer temp(temp_bytes);
    GSW_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(temp.as<void>(), temp_bytes, kb, vb,
                                                   static_cast<int>(M), 0, end_bit, stream));
  }
  if (vb.Current() != gauss_ids)
    GSW_CUDA_CHECK(cudaMemcpyAsync(gauss_ids, vb.Current(), sizeof(int32_t) * M,
                                   cudaMemcpyDeviceToDevice, stream));
  const uint64_t* sorted_keys = kb.Current();
  tile_offsets_kernel<<<blocks_for(M, kThreads), kThreads, 0, stream>>>(M, num_tiles,
                                                                         sorted_keys, tile_offsets);
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
