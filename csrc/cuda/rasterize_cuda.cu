// CUDA blending stage: forward, backward and per-Gaussian contribution, one thread block per
// 16x16 tile. The forward runs one thread per pixel, the contribution and the backward one per 4
// or 2 pixels (see below).
//
// Forward and contribution share one front-to-back traversal (traverse_tile): the tile's splats
// are staged in shared memory in batches of one splat per thread, every warp walks the batch's
// splats that reach its rows (row culling, below) in order with the CPU backend's per-pixel
// decisions (splat_alpha, blend_terminates from core/math.h) for each of its pixels, a warp leaves
// a batch as soon as all its pixels have terminated and the block stops at the first batch where
// all of them have. The traversal hands the blending weights w (0 where not blended) of the
// thread's pixels for each splat to a visitor;
// the forward accumulates colour/depth.
//
// The contribution's cost is its per-splat reduction over the warp (the weighted w per channel,
// hits and max w), not the blending: with one pixel per thread that reduction cost as much as the
// whole forward. So each of its threads owns PX = 4 (or 2) vertically adjacent pixels and first
// reduces over them in registers: one warp reduction per splat (a transposed butterfly for the
// channel sums, integer reductions for the hits and, in float32, for the max: non-negative floats
// order like their bit patterns) then covers 32 * PX pixels, and a warp skips it when
// none of them blended the splat. The pixels of a thread share their column, so the splat is read
// from shared memory once for all of them and the compiler shares the x terms of the Gaussian's
// exponent. Each warp stores its results for a splat in its own shared-memory slot (plain stores:
// shared-memory float atomics are compare-and-swap loops); after each batch, one thread per splat
// adds up the warps' slots and adds the block's totals to the splat's outputs with one atomic per
// value. A trained model's few dense tiles would set the kernel's length (one block each), so a
// tile longer than a chunk (about twice the mean share of one wave of blocks) is cut into chunks,
// one block each, every chunk starting from its pixels' transmittance in front of it: the product
// of the earlier chunks' own transmittances, walked first by chunk_prefix_kernel (TileChunks).
// GSW_CUDA_CONTRIBUTION=px4|px2 (A/B benchmarks only) walks whole tiles, densest first, with 4 or
// 2 pixels per thread instead.
//
// The backward walks each pixel back to front from its last blended splat (n_contrib), in
// batches from the tile's largest n_contrib down (a warp starts at its own largest), recovering
// T_i = T_{i+1} / (1 - alpha_i) as the CPU backend does. Its cost, like the contribution's, is
// the per-splat reduction of the ten cotangents (blend_backward_step, core/math.h: the same
// per-pixel step as the CPU backend's), so it has the same layout:
// each thread owns PX = 4 (or 2) vertically adjacent pixels of one column (a warp covers 32 /
// TILE_SIZE * PX whole rows), reads the splat from shared memory once for them and
// sums their ten cotangents in registers; a warp that blended the splat in none of its pixels skips
// it (one vote); otherwise a transposed butterfly (warp_sum_transposed: 12 shuffles instead of ten
// warp_sum()s' 50) leaves the ten warp sums in even lanes, which store them in the warp's
// shared-memory slot for the splat. After each batch one thread per splat adds up the warps'
// slots (in warp order) and stores the tile's totals as the intersection's record (kBlendGrads
// values per visited splat, in the tile's rows of the BlendRecords buffer, core/params.h; zeros
// where no pixel blended it; the splats behind the tile's last blended one get no record); a
// second kernel sums each Gaussian's records in intersection order (reduce_blend_grads,
// core/params.h, the CPU's reduction). No float atomics: the gradients are
// the same bits on every run, for kBlendGrads values of scratch per visited intersection. The alpha of each pixel is
// the forward's bit for bit (the same gaussian_power / splat_alpha), so exactly the splats the
// forward blended are undone; the exp() is shared with the VJP (splat_alpha_vjp_from_gaussian),
// as on the CPU. The blocks start with the tiles that visit the most splats (tile_order). When the
// densest tile's walk is longer than the time the busy tiles' total work keeps the GPU filled (a
// trained model's few dense tiles; any small image), every tile is walked with 2 pixels per thread
// instead of 4 (twice the warps per tile) and, when it is much longer, the tiles are cut into
// chunks instead (choose_layout_kernel, on the device, per render): a tile whose visited splats are
// longer than a chunk (128 splats, or the shortest length whose chunks fit one wave of checkpoint
// slots) is walked by one 4-pixel block per chunk. back_checkpoint_kernel first walks every chunk of such a
// tile front to back from T = 1 (its transmittance product and the colour and depth it adds, per
// pixel), and the block of chunk k starts each pixel that blends past the chunk from those (the
// transmittance in front of the chunk's end and the colour and depth behind it) instead of from
// T_final; a chunk's records are its own splats' rows, so the per-Gaussian sums are unchanged, and
// a tile of one chunk is walked as px4 walks it (BENCHMARKS.md 2s: on a lego model 1.7x / 3.5x
// faster than 2 pixels per thread at 800x800 / 400x400). GSW_CUDA_BACKWARD
// (A/B benchmarks only): "cut" cuts every render so (GSW_CUDA_CHUNK: at that length), "px4" / "px2"
// walk whole tiles with that layout; "atomic" adds the tile totals to the gradients with one atomic
// per value instead: no scratch, not bitwise deterministic.
#include <cstdlib>
#include <cstring>
#include <stdexcept>
#include <string>
#include <vector>

#include <cub/block/block_scan.cuh>
#include <cub/device/device_radix_sort.cuh>

#include "cuda/common.cuh"

namespace gsw::cuda {

namespace {

constexpr int kTilePixels = TILE_SIZE * TILE_SIZE;
constexpr int kBlock = kTilePixels;  // forward and backward: one thread per pixel
constexpr int kBatch = kBlock;       // splats staged per batch (one per thread)
static_assert(kBlock % 32 == 0 && kTilePixels / 4 % 32 == 0, "a tile must hold whole warps of 4-pixel threads");
constexpr int kVoteEvery = 8;  // splats between two "is the whole warp done?" votes
// Blend backward records up to this size (and the budget) are allocated for all M intersections
// without a host synchronisation; larger ones for the visited ones only (see rasterize_backward).
constexpr size_t kRecordsNoSyncBytes = size_t(64) << 20;
// Blend backward reduction: Gaussians with more intersections than this are reduced by a warp.
constexpr int kSerialEntries = 32;

// Shared-memory records, padded and aligned so that a thread reads one with 128-bit loads.
template <typename T>
struct alignas(4 * sizeof(T) < 16 ? 4 * sizeof(T) : 16) SplatGeo {
  T mx, my;
  T ca, cb, cc;
  T opacity;
  T pad0, pad1;
};
template <typename T>
struct alignas(4 * sizeof(T) < 16 ? 4 * sizeof(T) : 16) SplatColor {
  T r, g, b, depth;
};

template <typename T>
__device__ __forceinline__ SplatGeo<T> load_geo(const RasterParams<T>& p, int32_t g) {
  SplatGeo<T> s{};
  s.mx = p.means2d[2 * g];
  s.my = p.means2d[2 * g + 1];
  s.ca = p.conics[3 * g];
  s.cb = p.conics[3 * g + 1];
  s.cc = p.conics[3 * g + 2];
  s.opacity = p.opacities[g];
  return s;
}

template <typename T>
__device__ __forceinline__ T alpha_at(const SplatGeo<T>& s, T pxc, T pyc) {
  return splat_alpha(s.opacity, gaussian_power(Sym2<T>{s.ca, s.cb, s.cc}, s.mx, s.my, pxc, pyc));
}

// Row culling (forward and contribution): a warp's threads hold kWarpRows(PX) whole rows of the tile,
// and a warp skips the staged splats whose row mask (splat_row_mask, core/math.h) misses them: one
// ballot finds the warp's splats among 32 staged ones, so the skipped ones cost no alpha evaluations.
// The mask's y extent is widened by BIN_MARGIN pixels for the fast-math square root and division that
// compute it on the device; the rows left out are rows where every alpha is 0, so no result changes.
template <int PX>
constexpr int kWarpRows = 32 / TILE_SIZE * PX;
static_assert(32 % TILE_SIZE == 0 && TILE_SIZE <= 32, "a warp holds whole tile rows");

template <int PX>
__device__ __forceinline__ uint32_t warp_row_bits() {
  return ((1u << kWarpRows<PX>) - 1u) << (kWarpRows<PX> * static_cast<int>(threadIdx.x >> 5));
}

template <typename T>
__device__ __forceinline__ uint32_t row_mask(const SplatGeo<T>& s, int tile_y0) {
  return splat_row_mask(Sym2<T>{s.ca, s.cb, s.cc}, s.opacity, s.my, tile_y0, T(BIN_MARGIN));
}

// The PX pixels of this thread: (px, py + i) for i < PX. Thread t of the tile's block has column
// t % TILE_SIZE and first row PX * (t / TILE_SIZE).
template <int PX>
struct PixelCtx {
  int tile;
  int tile_y0;         // the tile's first pixel row
  int px, py;
  int rows;            // (px, py + i) is inside the image for i < rows
  int64_t pix;         // index of (px, py); (px, py + i) is pix + i * width
  int32_t start, end;  // the tile's range in the intersection list
  int local0;          // tile-local index of (px, py): row * TILE_SIZE + column
  __device__ __forceinline__ bool inside(int i = 0) const { return i < rows; }
  __device__ __forceinline__ int local(int i) const { return local0 + i * TILE_SIZE; }
};

template <int PX, typename T>
__device__ __forceinline__ PixelCtx<PX> pixel_ctx(const RasterParams<T>& p, int tile) {
  PixelCtx<PX> c;
  c.tile = tile;
  const int tx = c.tile % p.bins.tiles_x, ty = c.tile / p.bins.tiles_x;
  const int t = static_cast<int>(threadIdx.x);
  c.tile_y0 = ty * TILE_SIZE;
  c.px = tx * TILE_SIZE + t % TILE_SIZE;
  c.py = ty * TILE_SIZE + t / TILE_SIZE * PX;
  c.rows = c.px < p.width ? max(0, min(PX, p.height - c.py)) : 0;
  c.pix = int64_t(c.py) * p.width + c.px;
  c.start = p.bins.tile_offsets[c.tile];
  c.end = p.bins.tile_offsets[c.tile + 1];
  c.local0 = t / TILE_SIZE * PX * TILE_SIZE + t % TILE_SIZE;
  return c;
}

// Front-to-back traversal of this thread's pixels of its tile (see the file comment), with a
// block of kTilePixels / PX threads. The visitor provides
//   load(slot, g):       stage per-splat data of Gaussian g in shared slot `slot`;
//   blend(slot, w):      called by every thread of a warp for each splat the warp visits, with
//                        the weights w[i] = alpha T of this thread's pixels (0 when not blended);
//   end_batch(n):        called by every thread of the block after the n splats of a batch.
// The walk covers the intersections [c.start, c.end): the whole tile, or a chunk of it. On entry
// `tr` holds each pixel's transmittance in front of them (1 for a whole tile; a pixel with tr <
// T_MIN has terminated before); on return the final transmittances and `last` 1 + the index
// (from c.start) of the last blended splat (0 if none). Returns the pixels still blending (bit i:
// pixel i; a pixel that terminated keeps the transmittance in front of the splat that ended it).
template <int PX, typename T, typename Visitor>
__device__ __forceinline__ unsigned traverse_tile(const RasterParams<T>& p, const PixelCtx<PX>& c,
                                                  Visitor& vis, T (&tr)[PX], int32_t (&last)[PX]) {
  constexpr int kSplats = kTilePixels / PX;  // per batch: one per thread
  __shared__ SplatGeo<T> s_geo[kSplats];
  __shared__ uint32_t s_rows[kSplats];  // row_mask of each staged splat
  const uint32_t warp_rows = warp_row_bits<PX>();
  const int lane = static_cast<int>(threadIdx.x & 31);
  const T pxc = T(c.px) + T(0.5);
  T pyc[PX];
  unsigned live = 0;  // bit i: pixel i still blends (pixels outside never do)
#pragma unroll
  for (int i = 0; i < PX; ++i) {
    pyc[i] = T(c.py + i) + T(0.5);
    last[i] = 0;
    if (c.inside(i) && tr[i] >= T(T_MIN)) live |= 1u << i;
  }
  for (int32_t b = c.start; b < c.end; b += kSplats) {
    // Also the barrier before the shared batch is overwritten.
    if (!__syncthreads_or(live != 0)) break;
    const int32_t idx = b + static_cast<int32_t>(threadIdx.x);
    if (idx < c.end) {
      const int32_t g = p.bins.gauss_ids[idx];
      const SplatGeo<T> s = load_geo(p, g);
      s_geo[threadIdx.x] = s;
      s_rows[threadIdx.x] = row_mask(s, c.tile_y0);
      vis.load(threadIdx.x, g);
    }
    __syncthreads();
    const int n = min(kSplats, c.end - b);
    // The warp's splats in order, 32 staged ones per ballot (row culling, above). A warp leaves the
    // batch once all its pixels are done (checked every kVoteEvery splats it visits; done pixels
    // blend nothing, so when it is checked changes no result).
    int visits = 0;
    bool warp_done = false;
    for (int k32 = 0; k32 < n && !warp_done; k32 += 32) {
      unsigned todo = __ballot_sync(kFullMask, k32 + lane < n && (s_rows[k32 + lane] & warp_rows) != 0u);
      for (; todo != 0u; todo &= todo - 1u) {
        if ((visits++ % kVoteEvery) == 0 && !__any_sync(kFullMask, live != 0)) {
          warp_done = true;
          break;
        }
        const int k = k32 + __ffs(todo) - 1;
        const SplatGeo<T> s = s_geo[k];
        T w[PX];
#pragma unroll
        for (int i = 0; i < PX; ++i) {
          // alpha of done pixels too: no branch per pixel, and the compiler can share the terms of
          // the pixels' common column.
          const T alpha = alpha_at(s, pxc, pyc[i]);
          w[i] = T(0);
          if ((live >> i & 1u) && alpha > T(0)) {
            if (blend_terminates(tr[i], alpha)) {
              live &= ~(1u << i);  // this splat is not blended (INRIA)
            } else {
              w[i] = alpha * tr[i];
              tr[i] *= T(1) - alpha;
              last[i] = b - c.start + k + 1;
            }
          }
        }
        vis.blend(k, w);
      }
    }
    vis.end_batch(n);
  }
  return live;
}

// ------------------------------------------------------------------ tile schedules

// The blend backward's layouts, chosen per render on the device (choose_layout_kernel): whole tiles
// with 4 or 2 pixels per thread, or dense tiles cut into chunks (TileChunks).
constexpr int32_t kLayoutPx4 = 0, kLayoutPx2 = 1, kLayoutCut = 2;

// The tiles of one backward_kernel or contribution_kernel launch: block b takes tile order[b] (or
// tile0 + b without an order). With a layout flag (choose_layout_kernel's), the launch does nothing
// unless the flag chose its pixels per thread: every layout is launched, all but one return at once.
struct TileSchedule {
  const int32_t* order = nullptr;
  int tile0 = 0;
  const int32_t* layout = nullptr;
  __device__ __forceinline__ bool skips(int px) const {
    return layout != nullptr && *layout != (px == 2 ? kLayoutPx2 : kLayoutPx4);
  }
  __device__ __forceinline__ int tile() const {
    return order != nullptr ? order[blockIdx.x] : tile0 + static_cast<int>(blockIdx.x);
  }
};

// The layout thresholds kCriticalPathFactor and kCutFactor are in core/constants.h.

// ------------------------------------------------------------------ dense-tile chunks

// A trained model's few dense tiles set the length of a kernel that walks each tile with one block
// (BENCHMARKS.md 2k). The contribution cuts every tile longer than a chunk into chunks, one block
// each. A chunk starts from its pixels' transmittance in front of it: the product of the earlier
// chunks' own transmittances, each walked from T = 1 by chunk_prefix_kernel first. (The forward
// cut alike was 9 % faster on a lego model at 800x800 but 33 % slower at 1600x1600, where a cut
// tile's chunks behind its opaque front are walked from T = 1 too: BENCHMARKS.md 2o.)

// Chunk length: kCriticalPathFactor x the mean share of M intersections over one wave of `wave`
// resident blocks, at least kMinChunk, in whole batches of 4-pixel blocks.
// GSW_CUDA_CHUNK=N (tests and A/B benchmarks; read at every call) sets the length instead: a positive
// multiple of the 4-pixel batch (64 splats).
constexpr int32_t kMinChunk = 256;
inline int32_t env_chunk_length() {  // GSW_CUDA_CHUNK, 0 when unset or empty
  constexpr int64_t kSplats = kTilePixels / 4;
  const char* e = std::getenv("GSW_CUDA_CHUNK");
  if (e == nullptr || *e == '\0') return 0;
  char* end = nullptr;
  const long n = std::strtol(e, &end, 10);
  if (*end != '\0' || n <= 0 || n % kSplats != 0 || n > (1L << 30))
    throw std::invalid_argument(std::string("GSW_CUDA_CHUNK must be a positive multiple of ") +
                                std::to_string(kSplats) + " (splats per chunk), not '" + e + "'");
  return static_cast<int32_t>(n);
}
inline int32_t chunk_size(int64_t M, int64_t wave) {
  constexpr int64_t kSplats = kTilePixels / 4;
  if (const int32_t n = env_chunk_length(); n > 0) return n;
  const int64_t share = (kCriticalPathFactor * M + wave - 1) / (wave > 0 ? wave : 1);
  const int64_t size = share > kMinChunk ? share : kMinChunk;
  return static_cast<int32_t>((size + kSplats - 1) / kSplats * kSplats);
}

// Tile j's splat list (its intersections, or the blend backward's visited splats) is cut into
// offsets[j + 1] - offsets[j] >= 1 chunks of at most `size` splats, one block each: block b walks
// chunk offsets[t0] + b - offsets[j] of the tile j with offsets[j] <= offsets[t0] + b <
// offsets[j + 1], for the tiles [t0, t1) of the launch; blocks past chunk offsets[t1] do nothing.
// The tiles in front of tile j have slot0 = offsets[j] - j chunks beyond their first, so tile j's
// chunks k < n - 1 own the slots slot0 + k, kTilePixels values each (indexed by PixelCtx::local) in
// `prefix` and, for the blend backward, 4 x kTilePixels in `colour`.
// The contribution's prefix slot holds the product of (1 - alpha) over the splats its pixel blends
// in the chunk, walked from T = 1, or 0 where the pixel terminates in it. The product over the
// chunks in front is then below T_MIN exactly when the pixel has terminated in front of the chunk
// (transmittance only falls), and otherwise the transmittance a whole-tile walk reaches there, up
// to rounding. The blend backward's are back_checkpoint_kernel's. The blend backward's chunks
// are chosen on the device per render (choose_layout_kernel): `chosen` holds the layout flag and
// the length, and there are no chunks unless it chose kLayoutCut.
template <typename T>
struct TileChunks {
  const int32_t* offsets = nullptr;  // nullptr: no chunks (one block per tile)
  int t0 = 0, t1 = 0;
  int32_t size = 0;
  T* prefix = nullptr;
  T* colour = nullptr;
  const int32_t* chosen = nullptr;  // {layout flag, length} (choose_layout_kernel), or nullptr: `size`
  struct Chunk {
    int tile, k, n;  // chunk k of the tile's n
    int64_t slot0;   // chunks of the tiles in front beyond their first
  };
  __device__ __forceinline__ int32_t length() const { return chosen != nullptr ? chosen[1] : size; }
  // This block's chunk; false for a block past the last (or for every block unless cut).
  __device__ __forceinline__ bool find(Chunk& ch) const {
    if (chosen != nullptr && chosen[0] != kLayoutCut) return false;
    const int32_t b = offsets[t0] + static_cast<int32_t>(blockIdx.x);
    if (b >= offsets[t1]) return false;
    int lo = t0, n = t1 - t0;  // the last j with offsets[j] <= b (then offsets[j + 1] > b)
    while (n > 1) {
      const int half = n >> 1;
      lo = offsets[lo + half] <= b ? lo + half : lo;
      n -= half;
    }
    ch = Chunk{lo, b - offsets[lo], offsets[lo + 1] - offsets[lo], int64_t(offsets[lo]) - lo};
    return true;
  }
  // Narrows c to chunk ch of its tile's intersections.
  template <int PX>
  __device__ __forceinline__ void narrow(PixelCtx<PX>& c, const Chunk& ch) const {
    c.start += ch.k * length();
    c.end = min(c.end, c.start + length());
  }
  __device__ __forceinline__ T* prefix_slot(const Chunk& ch, int k) const {
    return prefix + (ch.slot0 + k) * kTilePixels;
  }
  __device__ __forceinline__ T* colour_slot(const Chunk& ch, int k, int channel) const {
    return colour + ((ch.slot0 + k) * 4 + channel) * kTilePixels;
  }
  // The transmittance in front of chunk k of ch's tile at tile-local pixel `local`: the product of
  // the prefix slots of the chunks in front, in order.
  __device__ __forceinline__ T front(const Chunk& ch, int k, int local) const {
    T tr = T(1);
    for (int m = 0; m < k; ++m) tr *= prefix_slot(ch, m)[local];
    return tr;
  }
};

// Chunks per tile (tile j: ceil(intersections / size), at least 1: an empty tile's block does
// nothing; tile `tiles`: 0, for the prefix sum's total).
__global__ void __launch_bounds__(kBlock)
    chunk_count_kernel(const int32_t* __restrict__ tile_offsets, int tiles, int32_t size, int32_t* __restrict__ n) {
  const int t = static_cast<int>(blockIdx.x * blockDim.x + threadIdx.x);
  if (t <= tiles) {
    const int32_t count = t < tiles ? tile_offsets[t + 1] - tile_offsets[t] : 0;
    n[t] = t < tiles ? (count > 0 ? (count - 1) / size + 1 : 1) : 0;
  }
}

// Walks nothing but the transmittance (traverse_tile's visitor for chunk_prefix_kernel).
struct NoVisitor {
  __device__ __forceinline__ void load(int, int32_t) {}
  template <typename W>
  __device__ __forceinline__ void blend(int, const W&) {}
  __device__ __forceinline__ void end_batch(int) {}
};

// The prefix slot of every chunk but each tile's last (TileChunks), 4 pixels per thread.
template <typename T>
__global__ void __launch_bounds__(kTilePixels / 4) chunk_prefix_kernel(const RasterParams<T> p,
                                                                       const TileChunks<T> chunks) {
  typename TileChunks<T>::Chunk ch;
  if (!chunks.find(ch) || ch.k == ch.n - 1) return;
  PixelCtx<4> c = pixel_ctx<4>(p, ch.tile);
  chunks.narrow(c, ch);
  NoVisitor vis;
  T tr[4] = {T(1), T(1), T(1), T(1)};
  int32_t last[4];
  const unsigned live = traverse_tile(p, c, vis, tr, last);
  T* out = chunks.prefix_slot(ch, ch.k);
#pragma unroll
  for (int i = 0; i < 4; ++i) out[c.local(i)] = (live >> i & 1u) ? tr[i] : T(0);
}

// The blend backward's checkpoints (TileChunks over each tile's visited splats, BlendRecords): for
// chunk m of a tile cut into n > 1 chunks and each pixel, the splats of the chunk it blended (in
// front of its n_contrib, alpha > 0: the forward's) walked front to back from T = 1: the product of
// their (1 - alpha) in prefix slot m (m < n - 1), and the colour and depth they add, per unit of
// the transmittance in front of the chunk, in colour slot m - 1 (m > 0). The backward of chunk k
// starts its pixels that blend past the chunk from these (BackPixel resume): no block walks more
// than one chunk, and nothing behind a pixel's last blended splat is walked. 4 pixels per thread.
template <typename T>
__global__ void __launch_bounds__(kTilePixels / 4)
    back_checkpoint_kernel(const RasterParams<T> p, const int32_t* __restrict__ visited, const TileChunks<T> chunks) {
  constexpr int PX = 4, kThreads = kTilePixels / PX;
  __shared__ SplatGeo<T> s_geo[kThreads];
  __shared__ SplatColor<T> s_col[kThreads];
  typename TileChunks<T>::Chunk ch;
  if (!chunks.find(ch) || ch.n == 1) return;
  const PixelCtx<PX> c = pixel_ctx<PX>(p, ch.tile);
  const int32_t size = chunks.length();
  const int j0 = ch.k * size, j1 = min(visited[ch.tile], j0 + size);
  const int t = static_cast<int>(threadIdx.x);
  const T pxc = T(c.px) + T(0.5);
  T pyc[PX], tr[PX], acc[PX][4];
  int n[PX], n_max = 0;
#pragma unroll
  for (int i = 0; i < PX; ++i) {
    pyc[i] = T(c.py + i) + T(0.5);
    n[i] = c.inside(i) ? p.n_contrib[c.pix + int64_t(i) * p.width] : 0;
    n_max = max(n_max, n[i]);
    tr[i] = T(1);
#pragma unroll
    for (int q = 0; q < 4; ++q) acc[i][q] = T(0);
  }
  const int warp_n = static_cast<int>(__reduce_max_sync(kFullMask, static_cast<unsigned>(n_max)));
  for (int lo = j0; lo < j1; lo += kThreads) {
    __syncthreads();  // the previous batch is consumed
    if (lo + t < j1) {
      const int32_t gid = p.bins.gauss_ids[c.start + lo + t];
      s_geo[t] = load_geo(p, gid);
      s_col[t] = {p.colors[3 * gid], p.colors[3 * gid + 1], p.colors[3 * gid + 2], p.depths[gid]};
    }
    __syncthreads();
    const int hi = min(min(j1, warp_n), lo + kThreads);
    for (int j = lo; j < hi; ++j) {
      const SplatGeo<T> s = s_geo[j - lo];
      const SplatColor<T> col = s_col[j - lo];
#pragma unroll
      for (int i = 0; i < PX; ++i) {
        const T a = j < n[i] ? alpha_at(s, pxc, pyc[i]) : T(0);
        if (a > T(0)) {
          const T w = a * tr[i];
          acc[i][0] += w * col.r;
          acc[i][1] += w * col.g;
          acc[i][2] += w * col.b;
          acc[i][3] += w * col.depth;
          tr[i] *= T(1) - a;
        }
      }
    }
  }
#pragma unroll
  for (int i = 0; i < PX; ++i) {
    if (ch.k < ch.n - 1) chunks.prefix_slot(ch, ch.k)[c.local(i)] = tr[i];
    if (ch.k > 0)
#pragma unroll
      for (int q = 0; q < 4; ++q) chunks.colour_slot(ch, ch.k - 1, q)[c.local(i)] = acc[i][q];
  }
}

// The contribution's chunks (TileChunks) of `size` splats of the tile lists whose prefix sum is
// `tile_offsets` (total <= `bound` splats): the chunk counts' prefix sum and a prefix slot per
// pixel and chunk, computed on the device (no host synchronisation); `grid` blocks cover every
// chunk, `extra` >= the chunks beyond each tile's first (their sum of ceil(n / size) - 1 is at most
// bound / size). The slots are not filled here.
template <typename T>
struct ChunkPlan {
  DeviceBuffer offsets, prefix;
  TileChunks<T> chunks;
  int64_t extra = 0;
  unsigned grid = 0;
};

template <typename T>
ChunkPlan<T> plan_chunks(const int32_t* tile_offsets, int64_t tiles, int64_t bound, int32_t size,
                         cudaStream_t stream) {
  const int64_t extra = bound / size;
  ChunkPlan<T> plan{DeviceBuffer(sizeof(int32_t) * size_t(2 * (tiles + 1))),
                    DeviceBuffer(sizeof(T) * size_t(extra) * kTilePixels)};
  int32_t* counts = plan.offsets.template as<int32_t>();
  int32_t* offsets = counts + tiles + 1;
  chunk_count_kernel<<<blocks_for(tiles + 1, kBlock), kBlock, 0, stream>>>(tile_offsets, static_cast<int>(tiles),
                                                                          size, counts);
  GSW_KERNEL_CHECK();
  exclusive_sum(counts, offsets, static_cast<int>(tiles + 1), stream);
  T* prefix = plan.prefix.template as<T>();
  plan.chunks = TileChunks<T>{offsets, 0, static_cast<int>(tiles), size, prefix};
  plan.extra = extra;
  plan.grid = static_cast<unsigned>(tiles + extra);
  return plan;
}

// ------------------------------------------------------------------ forward

template <typename T>
struct ForwardVisitor {
  const RasterParams<T>& p;
  SplatColor<T>* s_col;
  T r = T(0), g = T(0), b = T(0), d = T(0);
  __device__ void load(int slot, int32_t gid) {
    s_col[slot] = {p.colors[3 * gid], p.colors[3 * gid + 1], p.colors[3 * gid + 2],
                   p.depths[gid]};
  }
  __device__ __forceinline__ void end_batch(int) {}
  __device__ __forceinline__ void blend(int slot, const T (&w)[1]) {
    if (w[0] > T(0)) {
      const SplatColor<T> c = s_col[slot];
      r += w[0] * c.r;
      g += w[0] * c.g;
      b += w[0] * c.b;
      d += w[0] * c.depth;
    }
  }
};

template <typename T>
__global__ void __launch_bounds__(kBlock) forward_kernel(const RasterParams<T> p) {
  __shared__ SplatColor<T> s_col[kBatch];
  const PixelCtx<1> c = pixel_ctx<1>(p, blockIdx.x);
  ForwardVisitor<T> vis{p, s_col};
  T tr[1] = {T(1)};
  int32_t last[1];
  traverse_tile(p, c, vis, tr, last);
  if (!c.inside()) return;
  const int64_t P = int64_t(p.width) * p.height;
  p.image[c.pix] = vis.r + tr[0] * p.background[0];
  p.image[P + c.pix] = vis.g + tr[0] * p.background[1];
  p.image[2 * P + c.pix] = vis.b + tr[0] * p.background[2];
  p.alpha[c.pix] = T(1) - tr[0];
  p.depth[c.pix] = vis.d;
  p.final_T[c.pix] = tr[0];
  p.n_contrib[c.pix] = last[0];
}

// ------------------------------------------------------------------ contribution

// Per-batch shared results of the contribution: for each warp and staged splat, the warp's
// totals (part: the CT channel sums, then max w; hits), written by the warp only when it hit the
// splat (hits stays 0 otherwise), summed over the warps after the batch by one thread per slot.
template <typename T, int CT, int PX>
struct ContributionShared {
  static constexpr int kThreads = kTilePixels / PX, kWarps = kThreads / 32;
  T part[kWarps][CT + 1][kThreads];
  int32_t hits[kWarps][kThreads];
  int32_t gid[kThreads];
};

// Static shared memory of contribution_kernel<T, CT, PX>: its results and traverse_tile's staged batch.
template <typename T, int CT, int PX>
constexpr size_t contribution_shared_bytes() {
  return sizeof(ContributionShared<T, CT, PX>) + size_t(kTilePixels / PX) * (sizeof(SplatGeo<T>) + sizeof(uint32_t));
}

// CT > 0: C = CT channels, this thread's weights in registers, channel sums accumulated in shared
// memory; CT = 0: any C, weights read from global memory, channel sums added with one atomic per
// warp and channel (hits and max w through shared memory in both cases).
template <typename T, int CT, int PX>
struct ContributionVisitor {
  static_assert(CT == 0 || CT == 1 || CT == 3, "dispatched for C = 1, 3 or any (0)");
  static constexpr int kWarps = ContributionShared<T, CT, PX>::kWarps;
  const ContributionParams<T>& cp;
  int64_t P, pix;  // pixel i of this thread is pix + i * width
  int width;
  ContributionShared<T, CT, PX>* sh;
  T wreg[PX][CT > 0 ? CT : 1];
  __device__ void load(int slot, int32_t gid) {
    sh->gid[slot] = gid;
#pragma unroll
    for (int wp = 0; wp < kWarps; ++wp) sh->hits[wp][slot] = 0;
  }
  __device__ __forceinline__ void blend(int slot, const T (&w)[PX]) {
    // This thread's share: its pixels' sums, hits and max (w = 0 adds nothing).
    T sum[CT > 0 ? CT : 1];
    T m = T(0);
    int n = 0;
#pragma unroll
    for (int ch = 0; ch < CT; ++ch) sum[ch] = T(0);
#pragma unroll
    for (int i = 0; i < PX; ++i) {
      n += w[i] > T(0);
      m = max(m, w[i]);
#pragma unroll
      for (int ch = 0; ch < CT; ++ch) sum[ch] += w[i] * wreg[i][ch];
    }
    if (!__any_sync(kFullMask, n > 0)) return;  // warp-uniform: no pixel blended the splat
    const int hits = __reduce_add_sync(kFullMask, n);
    const T mw = warp_max_nonneg(m);
    const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
    if constexpr (CT == 3) {
      int q;
      const T x = warp_sum_transposed(sum, q);
      if ((lane & 7) == 0 && q >= 0) sh->part[warp][q][slot] = x;  // lanes 0, 8, 16
    } else if constexpr (CT == 1) {
      const T x = warp_sum(sum[0]);
      if (lane == 0) sh->part[warp][0][slot] = x;
    } else {
      const int C = cp.C;
      T* out = cp.contribution + int64_t(C) * sh->gid[slot];
      for (int ch = 0; ch < C; ++ch) {
        T v = T(0);
#pragma unroll
        for (int i = 0; i < PX; ++i)
          if (w[i] > T(0)) v += w[i] * cp.weights[ch * P + pix + int64_t(i) * width];
        v = warp_sum(v);
        if (lane == 0 && v != T(0)) atomicAdd(out + ch, v);
      }
    }
    if (lane == 0) {
      sh->part[warp][CT][slot] = mw;
      sh->hits[warp][slot] = hits;
    }
  }
  __device__ __forceinline__ void end_batch(int n) {
    __syncthreads();  // every warp has finished the batch
    const int slot = threadIdx.x;
    if (slot >= n) return;
    int32_t hits = 0;
    T v[CT + 1];  // channel sums, then max w
#pragma unroll
    for (int q = 0; q <= CT; ++q) v[q] = T(0);
#pragma unroll
    for (int wp = 0; wp < kWarps; ++wp) {
      const int32_t h = sh->hits[wp][slot];
      if (h == 0) continue;  // this warp wrote nothing for the splat
      hits += h;
#pragma unroll
      for (int ch = 0; ch < CT; ++ch) v[ch] += sh->part[wp][ch][slot];
      v[CT] = max(v[CT], sh->part[wp][CT][slot]);
    }
    if (hits == 0) return;
    const int32_t gid = sh->gid[slot];
    T* out = cp.contribution + int64_t(CT) * gid;
#pragma unroll
    for (int ch = 0; ch < CT; ++ch)
      if (v[ch] != T(0)) atomicAdd(out + ch, v[ch]);
    atomicAdd(cp.hits + gid, hits);
    atomic_max_nonneg(cp.max_weight + gid, v[CT]);
  }
};

// The contribution with PX pixels per thread: on the chunks of `chunks` when it has offsets, else
// on the tiles of `sched`.
template <typename T, int CT, int PX>
__global__ void __launch_bounds__(kTilePixels / PX)
    contribution_kernel(const RasterParams<T> p, const ContributionParams<T> cp, const TileSchedule sched,
                        const TileChunks<T> chunks) {
  static_assert(contribution_shared_bytes<T, CT, PX>() <= 48 * 1024, "static shared memory is limited to 48 KiB");
  __shared__ ContributionShared<T, CT, PX> sh;
  T tr[PX];
#pragma unroll
  for (int i = 0; i < PX; ++i) tr[i] = T(1);
  PixelCtx<PX> c;
  if (chunks.offsets != nullptr) {
    typename TileChunks<T>::Chunk ch;
    if (!chunks.find(ch)) return;
    c = pixel_ctx<PX>(p, ch.tile);
    chunks.narrow(c, ch);
#pragma unroll
    for (int i = 0; i < PX; ++i) tr[i] = chunks.front(ch, ch.k, c.local(i));
  } else {
    if (sched.skips(PX)) return;
    c = pixel_ctx<PX>(p, sched.tile());
  }
  const int64_t P = int64_t(p.width) * p.height;
  ContributionVisitor<T, CT, PX> vis{cp, P, c.pix, p.width, &sh};
  if constexpr (CT > 0) {
#pragma unroll
    for (int i = 0; i < PX; ++i)
#pragma unroll
      for (int ch = 0; ch < CT; ++ch)
        vis.wreg[i][ch] =
            c.inside(i) ? cp.weights[ch * P + c.pix + int64_t(i) * p.width] : T(0);
  }
  int32_t last[PX];
  traverse_tile(p, c, vis, tr, last);
}

// ------------------------------------------------------------------ backward

// Back-to-front state of one pixel (core/math.h's blend backward state and cotangents).
template <typename T>
struct BackPixel {
  T pyc;                     // pixel-centre y
  BlendBackwardPixel<T> st;  // transmittance and colour/depth behind the current splat
  PixelCotangents<T> cot;    // cotangents of the pixel's outputs, T_final
  int32_t n;                 // n_contrib: the splats at tile-local index >= n are not blended
};

template <typename T, int PX>
__device__ __forceinline__ BackPixel<T> load_back_pixel(const RasterParams<T>& p,
                                                        const RasterGradParams<T>& g,
                                                        const PixelCtx<PX>& c, int i) {
  BackPixel<T> q;
  q.pyc = T(c.py + i) + T(0.5);
  q.st.tr = q.cot.t_final = T(1);
  q.cot.v_t_final = q.cot.depth = T(0);
#pragma unroll
  for (int ch = 0; ch < 4; ++ch) q.st.behind[ch] = T(0);
#pragma unroll
  for (int ch = 0; ch < 3; ++ch) q.cot.color[ch] = T(0);
  q.n = 0;
  if (!c.inside(i)) return q;
  const int64_t P = int64_t(p.width) * p.height, pix = c.pix + int64_t(i) * p.width;
  q.n = p.n_contrib[pix];
  q.st.tr = q.cot.t_final = p.final_T[pix];
#pragma unroll
  for (int ch = 0; ch < 3; ++ch) q.cot.color[ch] = g.v_image[ch * P + pix];
  q.cot.depth = g.v_depth ? g.v_depth[pix] : T(0);
  q.cot.v_t_final = q.cot.color[0] * p.background[0] + q.cot.color[1] * p.background[1] + q.cot.color[2] * p.background[2] -
          (g.v_alpha ? g.v_alpha[pix] : T(0));
  return q;
}

// Shared memory of backward_kernel: the staged batch (one splat per thread) and, per warp and
// staged splat, the warp's ten cotangent sums.
template <typename T, int PX>
struct BackwardShared {
  static constexpr int kThreads = kTilePixels / PX, kWarps = kThreads / 32;
  SplatGeo<T> geo[kThreads];
  SplatColor<T> col[kThreads];
  int32_t gid[kThreads];
  // part[w][q][k]: warp w's sum of cotangent q of staged splat k, valid where hit[w][k] != 0.
  // The + 1 puts the ten values a warp stores for one splat into ten different banks.
  T part[kWarps][kBlendGrads][kThreads + 1];
  int32_t hit[kWarps][kThreads];
};

// Steps the thread's pixels back over staged splat k (tile-local index j) and, if any pixel of
// the warp blended it, stores the warp's sums of its cotangents in the warp's shared slot.
template <typename T, int PX>
__device__ __forceinline__ void backward_splat(BackwardShared<T, PX>& sh, int k, int j, T pxc,
                                               BackPixel<T> (&px)[PX]) {
  const SplatGeo<T> s = sh.geo[k];
  const Sym2<T> conic{s.ca, s.cb, s.cc};
  // The forward's alpha (alpha_at, bit for bit: gaussian_power has fixed roundings on the
  // device), so a > 0 exactly for the splats the forward blended in front of n_contrib.
  T a[PX], G[PX];
  bool any = false;
#pragma unroll
  for (int i = 0; i < PX; ++i) {
    const T power = gaussian_power(conic, s.mx, s.my, pxc, px[i].pyc);
    G[i] = splat_gaussian(power);
    a[i] = j < px[i].n ? splat_alpha_from_gaussian(s.opacity, power, G[i]) : T(0);
    any |= a[i] > T(0);
  }
  if (!__any_sync(kFullMask, any)) return;  // warp-uniform: no pixel of the warp blended it
  const SplatColor<T> col = sh.col[k];
  T v[kBlendGrads];  // this thread's sums over its pixels
#pragma unroll
  for (int q = 0; q < kBlendGrads; ++q) v[q] = T(0);
#pragma unroll
  for (int i = 0; i < PX; ++i) {
    if (!(a[i] > T(0))) continue;
    BackPixel<T>& pp = px[i];
    const BlendGrad<T> bg = blend_backward_step(
        SplatAtPixel<T>{conic, s.mx - pxc, s.my - pp.pyc, G[i], s.opacity, a[i], {col.r, col.g, col.b}, col.depth},
        pp.cot, pp.st);
    add_blend_grad(bg, v);
  }
  // The ten warp sums in 12 shuffles; each lands in a pair of lanes (2l, 2l + 1).
  int q;
  const T x = warp_sum_transposed(v, q);
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  if ((lane & 1) == 0 && q >= 0) sh.part[warp][q][k] = x;
  if (lane == 0) sh.hit[warp][k] = 1;
}

// Cotangent q of Gaussian gid in the outputs.
template <typename T>
__device__ __forceinline__ T* splat_grad_ptr(const RasterGradParams<T>& g, int q, int32_t gid) {
  if (q < 2) return g.v_means2d + 2 * int64_t(gid) + q;
  if (q < 5) return g.v_conics + 3 * int64_t(gid) + (q - 2);
  if (q == 5) return g.v_opacities + gid;
  if (q < 9) return g.v_colors + 3 * int64_t(gid) + (q - 6);
  return g.v_depths + gid;
}

// After a batch: the block's totals of staged splat k (the warps' slots, in warp order), stored
// as its intersection's record `rec` (zeros when no warp blended it) or, Atomic, added to the
// outputs with one atomic per nonzero value.
template <typename T, int PX, bool Atomic>
__device__ __forceinline__ void flush_splat(const RasterGradParams<T>& g,
                                            const BackwardShared<T, PX>& sh, int k, T* rec) {
  T v[kBlendGrads];
#pragma unroll
  for (int q = 0; q < kBlendGrads; ++q) v[q] = T(0);
  bool hit = false;
#pragma unroll
  for (int w = 0; w < BackwardShared<T, PX>::kWarps; ++w) {
    if (sh.hit[w][k] == 0) continue;
    hit = true;
#pragma unroll
    for (int q = 0; q < kBlendGrads; ++q) v[q] += sh.part[w][q][k];
  }
  if constexpr (Atomic) {
    if (!hit) return;
    const int32_t gid = sh.gid[k];
#pragma unroll
    for (int q = 0; q < kBlendGrads; ++q)
      if (v[q] != T(0)) atomicAdd(splat_grad_ptr(g, q, gid), v[q]);
  } else {
#pragma unroll
    for (int q = 0; q < kBlendGrads; ++q) rec[q] = v[q];
  }
}

// Resident blocks per SM that the float chunked backward is compiled for: those of the whole-tile
// 4-pixel kernel (at most 102 registers; without the bound the chunk bookkeeping takes 115).
constexpr int kCutBlocksPerSM = 10;

// Starts pixel q of chunk ch (of its tile's visited splats, ending at j1) where it blends past the
// chunk: from the transmittance in front of splat j1 (the product of the checkpoints' transmittances
// of the chunks up to ch) and the colour and depth behind it (the later chunks' checkpoints, back to
// front: behind = colour_m + (1 - alpha)-product_m x behind). A pixel whose last blended splat lies
// in the chunk starts as in a whole-tile walk (T_final, nothing behind).
template <typename T>
__device__ __forceinline__ void resume(const TileChunks<T>& chunks, const typename TileChunks<T>::Chunk& ch, int j1,
                                       int local, BackPixel<T>& q) {
  if (q.n <= j1) return;
  q.st.tr = chunks.front(ch, ch.k + 1, local);
  T behind[4] = {T(0), T(0), T(0), T(0)};
  for (int m = ch.n - 1; m > ch.k; --m) {
    const T keep = m < ch.n - 1 ? chunks.prefix_slot(ch, m)[local] : T(0);
#pragma unroll
    for (int c = 0; c < 4; ++c) behind[c] = chunks.colour_slot(ch, m - 1, c)[local] + keep * behind[c];
  }
#pragma unroll
  for (int c = 0; c < 4; ++c) q.st.behind[c] = behind[c];
}

// Blend backward with PX vertically adjacent pixels per thread (see the file comment): on the
// chunks of `chunks` (Cut; back_checkpoint_kernel first), else on the whole tiles of `sched`.
// `records` (unless Atomic): the BlendRecords buffer (core/params.h); this tile's rows
// layout.offsets[tile] - layout.row0 + [0, layout.visited[tile]) are all written.
template <typename T, int PX, bool Atomic, bool Cut = false>
__global__ void __launch_bounds__(kTilePixels / PX, Cut && sizeof(T) == 4 ? kCutBlocksPerSM : 1)
    backward_kernel(const RasterParams<T> p, const RasterGradParams<T> g, const BlendRecords layout,
                    T* __restrict__ records, const TileSchedule sched, const TileChunks<T> chunks) {
  using Shared = BackwardShared<T, PX>;
  static_assert(sizeof(Shared) <= 48 * 1024, "static shared memory is limited to 48 KiB");
  constexpr int kThreads = Shared::kThreads;
  __shared__ Shared sh;
  typename TileChunks<T>::Chunk ch{};
  int tile;
  if constexpr (Cut) {
    if (!chunks.find(ch)) return;
    tile = ch.tile;
  } else {
    if (sched.skips(PX)) return;
    tile = sched.tile();
  }
  const PixelCtx<PX> c = pixel_ctx<PX>(p, tile);
  const T pxc = T(c.px) + T(0.5);
  // The splats [j0, j1) of the tile's list: its visited ones, or one chunk of them.
  int j0 = 0, j1 = layout.visited[c.tile];
  if constexpr (Cut) {
    const int32_t size = chunks.length();
    j0 = ch.k * size;
    j1 = min(j1, j0 + size);
  }
  BackPixel<T> px[PX];
  int n_max = 0;
#pragma unroll
  for (int i = 0; i < PX; ++i) {
    px[i] = load_back_pixel(p, g, c, i);
    if constexpr (Cut)
      if (ch.n > 1) resume(chunks, ch, j1, c.local(i), px[i]);
    n_max = max(n_max, static_cast<int>(px[i].n));
  }
  // The block walks the batches from j1 down; a warp visits only the splats in front of its own
  // largest n_contrib.
  const int warp_n = static_cast<int>(__reduce_max_sync(kFullMask, static_cast<unsigned>(n_max)));
  T* const tile_records = Atomic ? nullptr : records + int64_t(kBlendGrads) * (layout.offsets[c.tile] - layout.row0);
  const int t = static_cast<int>(threadIdx.x);
  for (int hi = j1; hi > j0; hi -= kThreads) {
    const int lo = hi - kThreads > j0 ? hi - kThreads : j0;
    __syncthreads();  // the previous batch is consumed and flushed
    if (lo + t < hi) {
      const int32_t gid = p.bins.gauss_ids[c.start + lo + t];
      sh.gid[t] = gid;
      sh.geo[t] = load_geo(p, gid);
      sh.col[t] = {p.colors[3 * gid], p.colors[3 * gid + 1], p.colors[3 * gid + 2], p.depths[gid]};
#pragma unroll
      for (int w = 0; w < Shared::kWarps; ++w) sh.hit[w][t] = 0;
    }
    __syncthreads();
    for (int k = min(hi, warp_n) - lo - 1; k >= 0; --k) backward_splat(sh, k, lo + k, pxc, px);
    __syncthreads();  // every warp has stored its sums of the batch
    if (lo + t < hi)
      flush_splat<T, PX, Atomic>(g, sh, t, Atomic ? nullptr : tile_records + int64_t(kBlendGrads) * (lo + t));
  }
}

// Record layout, first pass: each tile's visited count, the largest n_contrib of its pixels (one
// block per tile, one thread per pixel; visited[tiles] = 0 for the prefix sum's total), its index in
// ids[tile] (the values tile_order sorts), and the largest count in *max_visited (zeroed by the
// caller).
template <typename T>
__global__ void __launch_bounds__(kBlock)
    tile_visited_kernel(const RasterParams<T> p, int32_t* __restrict__ visited, int32_t* __restrict__ ids,
                        int32_t* __restrict__ max_visited) {
  __shared__ int32_t tile_max;
  const PixelCtx<1> c = pixel_ctx<1>(p, blockIdx.x);
  const int n = c.inside() ? p.n_contrib[c.pix] : 0;
  if (threadIdx.x == 0) tile_max = 0;
  __syncthreads();
  const int warp_n = static_cast<int>(__reduce_max_sync(kFullMask, static_cast<unsigned>(n)));
  if ((threadIdx.x & 31) == 0 && warp_n > 0) atomicMax(&tile_max, warp_n);
  __syncthreads();
  if (threadIdx.x == 0) {
    visited[c.tile] = tile_max;
    ids[c.tile] = c.tile;
    if (c.tile == 0) visited[gridDim.x] = 0;
    if (tile_max > 0) atomicMax(max_visited, tile_max);
  }
}

// The chunk lengths a dense render's blend backward may cut at: cut_length(0 .. kNumCutLengths - 1)
// of core/constants.h, shortest first.
static_assert(cut_length(0) % (kTilePixels / 4) == 0 && cut_length(1) % (kTilePixels / 4) == 0,
              "cut lengths are whole 4-pixel batches");
constexpr int kChooseThreads = 1024;

// The blend backward's layout for this render (one block; visited / offsets: the tiles' visited
// splats and their prefix sum), in choice[0]: kLayoutPx4 when the densest tile's walk (*max_count)
// is at most kCriticalPathFactor x the total walk (offsets[tiles]) shared by `wave` resident
// 4-pixel blocks: the GPU is filled and 4 pixels per thread, the higher throughput, win. Otherwise
// the kernel is as long as that tile's walk by one block, whatever the other SMs do. Above
// kCutFactor x the share, the tiles are cut into chunks of the shortest length of cut_length
// (choice[1]) whose chunks beyond each tile's first fit `capacity` checkpoint slots (kLayoutCut;
// choice[2 ...]: the chunk counts' prefix sum over the tiles, TileChunks::offsets); below it, or
// where no length fits or cuts the densest tile, every tile is walked whole with 2 pixels per
// thread: twice the warps (kLayoutPx2, HasPx2; else 4).
// force_cut (GSW_CUDA_BACKWARD=cut): cut whatever the balance; `length` > 0 (GSW_CUDA_CHUNK): cut at
// that length (the caller's capacity covers it).
template <bool HasPx2>
__global__ void __launch_bounds__(kChooseThreads)
    choose_layout_kernel(const int32_t* __restrict__ visited, const int32_t* __restrict__ offsets, int tiles,
                         const int32_t* __restrict__ max_count, int64_t wave, int64_t capacity, bool force_cut,
                         int32_t length, int32_t* __restrict__ choice) {
  using Scan = cub::BlockScan<int32_t, kChooseThreads>;
  __shared__ typename Scan::TempStorage scan;
  __shared__ int32_t extra[kNumCutLengths];
  __shared__ int32_t chosen;
  const int t = static_cast<int>(threadIdx.x);
  const int32_t most = *max_count;
  const bool dense = int64_t(most) * wave > int64_t(kCriticalPathFactor) * offsets[tiles];
  const bool cut_dense = int64_t(most) * wave > int64_t(kCutFactor) * offsets[tiles];
  if (!cut_dense && !force_cut) {
    if (t == 0) choice[0] = dense && HasPx2 ? kLayoutPx2 : kLayoutPx4, choice[1] = 0;
    return;
  }
  if (t < kNumCutLengths) extra[t] = 0;
  __syncthreads();
  if (length == 0) {  // the chunks beyond each tile's first, per length
    int32_t mine[kNumCutLengths] = {};
    for (int j = t; j < tiles; j += kChooseThreads) {
      const int32_t v = visited[j];
#pragma unroll
      for (int l = 0; l < kNumCutLengths; ++l) mine[l] += v > 0 ? (v - 1) / cut_length(l) : 0;
    }
#pragma unroll
    for (int l = 0; l < kNumCutLengths; ++l)
      if (mine[l] > 0) atomicAdd(&extra[l], mine[l]);
  }
  __syncthreads();
  if (t == 0) {
    int32_t len = length;
    for (int l = 0; len == 0 && l < kNumCutLengths; ++l)
      if (extra[l] <= capacity) len = cut_length(l);
    const bool cut = len > 0 && (force_cut || (cut_dense && len < most));
    choice[0] = cut ? kLayoutCut : (dense && HasPx2 ? kLayoutPx2 : kLayoutPx4);
    choice[1] = chosen = cut ? len : 0;
  }
  __syncthreads();
  if (chosen == 0) return;
  // Chunks per tile (ceil(visited / length), at least 1: an empty tile's block does nothing; 0 for
  // the total at index `tiles`), summed over a contiguous range of tiles per thread, then scanned.
  const int per = (tiles + 1 + kChooseThreads - 1) / kChooseThreads, lo = t * per, hi = min(tiles + 1, lo + per);
  auto chunks_of = [&](int j) { return j < tiles ? (visited[j] > 0 ? (visited[j] - 1) / chosen + 1 : 1) : 0; };
  int32_t sum = 0;
  for (int j = lo; j < hi; ++j) sum += chunks_of(j);
  Scan(scan).ExclusiveSum(sum, sum);
  for (int j = lo; j < hi; ++j) {
    choice[2 + j] = sum;
    sum += chunks_of(j);
  }
}

// The tile counts of the contribution's whole-tile layouts: each tile's intersections in
// counts[tile] and its index in ids[tile] (the values tile_order sorts).
__global__ void __launch_bounds__(kBlock)
    tile_count_kernel(const int32_t* __restrict__ tile_offsets, int tiles, int32_t* __restrict__ counts,
                      int32_t* __restrict__ ids) {
  const int t = static_cast<int>(blockIdx.x * blockDim.x + threadIdx.x);
  if (t < tiles) {
    counts[t] = tile_offsets[t + 1] - tile_offsets[t];
    ids[t] = t;
  }
}

// The intersections of tiles [t0, t1) (a chunk of a chunked backward, added onto the stored sums)
// or, for the whole image in one pass, all of them from zero.
__device__ __forceinline__ SlotSpan chunk_span(const TileBins& bins, int t0, int t1) {
  if (t0 == 0 && t1 == bins.tiles_x * bins.tiles_y) return SlotSpan{};
  return SlotSpan{bins.tile_offsets[t0], bins.tile_offsets[t1], true};
}

// Gaussian i with intersections in `span`: with at most kSerialEntries of them, its records summed
// in intersection order by this thread (reduce_blend_grads, as on the CPU); otherwise appended to
// `big` (big[0]: their count, zeroed by the caller) for reduce_big_kernel.
template <typename T>
__device__ __forceinline__ void reduce_or_defer(const RasterParams<T>& p, const RasterGradParams<T>& g,
                                                const BlendRecords& layout, const T* records, int32_t* big,
                                                int32_t i, const SlotSpan& span) {
  if (p.bins.entry_offsets[i + 1] - p.bins.entry_offsets[i] <= kSerialEntries)
    reduce_blend_grads(p.bins, layout, records, g, i, span);
  else
    big[1 + atomicAdd(big, 1)] = i;
}

// Second pass of a one-pass backward: reduce_or_defer for every Gaussian (from zero: those without
// intersections get zero cotangents).
template <typename T>
__global__ void __launch_bounds__(kBlock)
    reduce_blend_grads_kernel(const RasterParams<T> p, const RasterGradParams<T> g, const BlendRecords layout,
                              const T* __restrict__ records, int32_t* __restrict__ big) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < p.N) reduce_or_defer(p, g, layout, records, big, static_cast<int32_t>(i), SlotSpan{});
}

// Second pass of a chunk of tiles [t0, t1) in a chunked backward: reduce_or_defer for the Gaussians
// with intersections in the chunk only (the others keep their stored sums), found from the chunk's
// sorted positions instead of a pass over all N: the
// thread of position s handles Gaussian gauss_ids[s] when s is its first intersection in the chunk
// (a bisection over its entry slots, which grow with the entry). Grid-stride over the positions.
template <typename T>
__global__ void __launch_bounds__(kBlock)
    reduce_chunk_kernel(const RasterParams<T> p, const RasterGradParams<T> g, const BlendRecords layout,
                        const T* __restrict__ records, int32_t* __restrict__ big, int t0, int t1) {
  const SlotSpan span = chunk_span(p.bins, t0, t1);
  const int64_t stride = int64_t(gridDim.x) * blockDim.x;
  for (int64_t s = span.lo + int64_t(blockIdx.x) * blockDim.x + threadIdx.x; s < span.hi; s += stride) {
    const int32_t i = p.bins.gauss_ids[s];
    int32_t lo = p.bins.entry_offsets[i], n = p.bins.entry_offsets[i + 1] - lo;
    const int32_t e0 = lo;
    while (n > 1) {  // the entry holding s: the last e with entry_slots[e] <= s
      const int32_t half = n >> 1;
      lo = p.bins.entry_slots[lo + half] <= s ? lo + half : lo;
      n -= half;
    }
    if (lo > e0 && p.bins.entry_slots[lo - 1] >= span.lo) continue;  // not its first in the chunk
    reduce_or_defer(p, g, layout, records, big, i, span);
  }
}

// Second pass, Gaussians with more intersections (a large splat spans thousands of tiles): a warp
// each (grid-stride over `big`); lane l sums the records of intersections e0 + l, e0 + l + 32, ...
// in that order (add_blend_records), then the warp adds the lanes' sums with one transposed
// butterfly. The lanes and the butterfly's order depend on nothing but the Gaussian, so the
// gradients are the same bits on every run (in which order the Gaussians were appended to `big`
// does not matter). In a chunked backward each chunk's sum of a Gaussian's records (of tiles
// [t0, t1)) is added to its stored sums: a fixed order again.
template <typename T>
__global__ void __launch_bounds__(kBlock)
    reduce_big_kernel(const RasterParams<T> p, const RasterGradParams<T> g, const BlendRecords layout,
                      const T* __restrict__ records, const int32_t* __restrict__ big, int t0, int t1) {
  const int lane = static_cast<int>(threadIdx.x & 31);
  const int64_t warps = int64_t(gridDim.x) * (blockDim.x / 32);
  const int32_t n_big = big[0];
  const SlotSpan span = chunk_span(p.bins, t0, t1);
  for (int64_t w = int64_t(blockIdx.x) * (blockDim.x / 32) + threadIdx.x / 32; w < n_big; w += warps) {
    const int32_t i = big[1 + w];
    T acc[kBlendGrads];
#pragma unroll
    for (int k = 0; k < kBlendGrads; ++k) acc[k] = T(0);
    add_blend_records(p.bins, layout, records, i, span, lane, 32, acc);
    int index;
    const T sum = warp_sum_transposed(acc, index);
    __shared__ T out[kBlock / 32][kBlendGrads];
    if (index >= 0 && (lane & 1) == 0) out[threadIdx.x / 32][index] = sum;
    __syncwarp();
    if (lane == 0) {
      T* o = out[threadIdx.x / 32];
      if (span.accumulate) {
        T stored[kBlendGrads];
        load_blend_grads(g, i, stored);
#pragma unroll
        for (int k = 0; k < kBlendGrads; ++k) o[k] = stored[k] + o[k];
      }
      store_blend_grads(g, i, o);
    }
    __syncwarp();
  }
}

// The tiles' indices in decreasing order of their visited splats (ties in index order) as the block
// order of the blend backward (or of their intersections, the contribution's); visited / ids:
// tile_visited_kernel's (tile_count_kernel's), max_visited >= each count. A
// block is one tile, and blocks start roughly in index order: a dense tile that starts in the last
// wave of blocks prolongs the whole kernel by its own time. Started first (longest-processing-time-
// first), it runs beside the others. The order changes no result: every tile's block computes the
// same values wherever it runs. max_visited <= 0: nothing is sorted (an empty buffer).
DeviceBuffer tile_order(const int32_t* visited, const int32_t* ids, int64_t tiles, int64_t max_visited,
                        cudaStream_t stream) {
  if (max_visited <= 0 || tiles <= 0) return DeviceBuffer(0);
  const int n = static_cast<int>(tiles);
  DeviceBuffer sorted_visited(sizeof(int32_t) * size_t(n)), order(sizeof(int32_t) * size_t(n));
  int end_bit = 1;  // the counts' significant bits
  while (end_bit < 31 && (int64_t(1) << end_bit) <= max_visited) ++end_bit;
  size_t temp_bytes = 0;
  GSW_CUDA_CHECK(cub::DeviceRadixSort::SortPairsDescending(nullptr, temp_bytes, visited, sorted_visited.as<int32_t>(),
                                                           ids, order.as<int32_t>(), n, 0, end_bit, stream));
  DeviceBuffer temp(temp_bytes);
  GSW_CUDA_CHECK(cub::DeviceRadixSort::SortPairsDescending(temp.as<void>(), temp_bytes, visited,
                                                           sorted_visited.as<int32_t>(), ids, order.as<int32_t>(), n,
                                                           0, end_bit, stream));
  return order;
}

template <typename T>
int64_t num_tiles(const RasterParams<T>& p) {
  return int64_t(p.bins.tiles_x) * p.bins.tiles_y;
}

// Which blend backward runs: a benchmarking switch, read at every call from the environment
// variable GSW_CUDA_BACKWARD: "auto" (the default, also when unset or empty: whole tiles with 4
// pixels per thread, or dense tiles cut into chunks, or whole tiles with 2, as choose_layout_kernel
// decides), "cut" (tiles longer than a chunk cut into chunks on every render), "px4" / "px2" (whole
// tiles, 4 / 2 pixels per thread on every render) or "atomic" (px4 adding the tile totals with
// atomics: the former design, not bitwise deterministic). float64 runs px4 for px2: px2's shared
// memory would not fit.
// Anything else is an error.
// GSW_CUDA_CONTRIBUTION chooses the contribution's: "auto" (default: dense tiles cut into chunks),
// "px4" or "px2" (whole tiles; float64: px2 only where its shared memory fits, else px4).
enum class Variant { kAtomic, kAuto, kCut, kPx2, kPx4 };

Variant layout_variant(const char* name, bool backward) {
  const char* e = std::getenv(name);
  if (e == nullptr || *e == '\0' || std::strcmp(e, "auto") == 0) return Variant::kAuto;
  if (std::strcmp(e, "px4") == 0) return Variant::kPx4;
  if (std::strcmp(e, "px2") == 0) return Variant::kPx2;
  if (backward && std::strcmp(e, "cut") == 0) return Variant::kCut;
  if (backward && std::strcmp(e, "atomic") == 0) return Variant::kAtomic;
  throw std::invalid_argument(std::string(name) + " must be auto, px4, px2" + (backward ? ", cut or atomic" : "") +
                              " (or unset), not '" + e + "'");
}

// Streaming multiprocessors of the current device.
int device_sms() {
  int device = 0, sms = 0;
  GSW_CUDA_CHECK(cudaGetDevice(&device));
  GSW_CUDA_CHECK(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, device));
  return sms;
}

// Resident 4-pixel blocks of `kernel` on the whole device: one wave (choose_layout_kernel).
template <typename Kernel>
int64_t wave_of(Kernel kernel, int threads, int sms) {
  int per_sm = 0;
  GSW_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, kernel, threads, 0));
  return int64_t(per_sm) * sms;
}

}  // namespace

template <typename T>
void rasterize_forward(const RasterParams<T>& p) {
  const int64_t tiles = num_tiles(p);
  if (tiles <= 0) return;
  forward_kernel<T><<<static_cast<unsigned>(tiles), kBlock, 0, current_stream()>>>(p);
  GSW_KERNEL_CHECK();
}

template <typename T>
void rasterize_backward(const RasterParams<T>& p, const RasterGradParams<T>& g, int64_t budget_rows) {
  cudaStream_t stream = current_stream();
  const int64_t tiles = num_tiles(p);
  const Variant variant = layout_variant("GSW_CUDA_BACKWARD", true);
  auto zero_grads = [&] {
    const size_t n = size_t(p.N) * sizeof(T);
    GSW_CUDA_CHECK(cudaMemsetAsync(g.v_means2d, 0, 2 * n, stream));
    GSW_CUDA_CHECK(cudaMemsetAsync(g.v_conics, 0, 3 * n, stream));
    GSW_CUDA_CHECK(cudaMemsetAsync(g.v_colors, 0, 3 * n, stream));
    GSW_CUDA_CHECK(cudaMemsetAsync(g.v_opacities, 0, n, stream));
    GSW_CUDA_CHECK(cudaMemsetAsync(g.v_depths, 0, n, stream));
  };
  if (tiles <= 0 || p.N <= 0 || p.bins.M <= 0 || variant == Variant::kAtomic) {
    zero_grads();
    if (tiles <= 0 || p.N <= 0 || p.bins.M <= 0) return;
  }
  const unsigned grid = static_cast<unsigned>(tiles);
  // Record layout (BlendRecords): each tile's visited count and their prefix sum; then each tile's
  // index (tile_order's values) and the largest count.
  DeviceBuffer layout_buf(sizeof(int32_t) * (3 * tiles + 3));
  int32_t* visited = layout_buf.as<int32_t>();
  int32_t* offsets = visited + tiles + 1;
  int32_t* ids = offsets + tiles + 1;
  int32_t* max_visited = ids + tiles;
  GSW_CUDA_CHECK(cudaMemsetAsync(max_visited, 0, sizeof(int32_t), stream));
  tile_visited_kernel<T><<<grid, kBlock, 0, stream>>>(p, visited, ids, max_visited);
  GSW_KERNEL_CHECK();
  BlendRecords layout{visited, offsets};
  if (variant == Variant::kAtomic) {
    backward_kernel<T, 4, true><<<grid, kTilePixels / 4, 0, stream>>>(p, g, layout, nullptr, TileSchedule{},
                                                                       TileChunks<T>{});
    GSW_KERNEL_CHECK();
    return;
  }
  exclusive_sum(visited, offsets, static_cast<int>(tiles + 1), stream);
  // Chunks [t0, t1) of whole tiles and the rows the record buffer needs. Records of all M
  // intersections up to kRecordsNoSyncBytes and the budget are one chunk, allocated without a host
  // synchronisation; otherwise the layout is read back first: the visited ones only, in chunks of
  // at most budget_rows records (a tile with more is a chunk of its own).
  std::vector<std::pair<int64_t, int64_t>> chunks{{0, tiles}};
  int64_t rows = p.bins.M;
  std::vector<int32_t> host;  // the layout's offsets, when read back
  if (size_t(rows) * kBlendGrads * sizeof(T) > kRecordsNoSyncBytes || (budget_rows >= 0 && rows > budget_rows)) {
    host.resize(size_t(tiles) + 1);
    GSW_CUDA_CHECK(cudaMemcpyAsync(host.data(), offsets, sizeof(int32_t) * (tiles + 1), cudaMemcpyDeviceToHost, stream));
    GSW_CUDA_CHECK(cudaStreamSynchronize(stream));
    rows = host[tiles];
    if (budget_rows >= 0 && rows > budget_rows) {
      rows = plan_record_chunks(host.data(), tiles, budget_rows, chunks);
      zero_grads();  // each chunk adds to the gradients
    }
  }
  DeviceBuffer records(size_t(rows) * kBlendGrads * sizeof(T));
  T* rec = records.as<T>();
  constexpr bool kHasPx2 = sizeof(BackwardShared<T, 2>) <= 48 * 1024;  // float64: px2's shared memory would not fit
  const bool px2 = kHasPx2 && variant == Variant::kPx2;
  const bool choose = variant == Variant::kAuto || variant == Variant::kCut;  // on the device, per render
  DeviceBuffer big_buf(sizeof(int32_t) * (size_t(p.N) + 1));
  int32_t* big = big_buf.as<int32_t>();
  const int sms = device_sms();
  // auto / cut: choose_layout_kernel picks whole tiles (px4, px2) or chunks; a cut render's chunks
  // start from back_checkpoint_kernel's checkpoints, `capacity` slots of them: the chunks beyond
  // each tile's first at the shortest length of cut_length, up to one wave of 4-pixel blocks (or
  // every chunk at GSW_CUDA_CHUNK's length). The choice comes from the whole image's counts, so
  // every chunk of tiles of a records budget walks a tile alike (the same bits).
  const int32_t length = choose ? env_chunk_length() : 0;
  const int64_t capacity =
      !choose ? 0
      : length > 0
          ? p.bins.M / length
          : std::min<int64_t>(wave_of(backward_kernel<T, 4, false, true>, kTilePixels / 4, sms),
                              (p.bins.M + cut_length(0) - 1) / cut_length(0));
  DeviceBuffer choice_buf(sizeof(int32_t) * (choose ? size_t(tiles) + 3 : 0));
  DeviceBuffer checkpoints(sizeof(T) * size_t(capacity) * kTilePixels * 5);
  int32_t* choice = choice_buf.as<int32_t>();
  TileChunks<T> cuts{};
  if (choose) {
    choose_layout_kernel<kHasPx2><<<1, kChooseThreads, 0, stream>>>(
        visited, offsets, static_cast<int>(tiles), max_visited,
        wave_of(backward_kernel<T, 4, false>, kTilePixels / 4, sms), capacity, variant == Variant::kCut, length,
        choice);
    GSW_KERNEL_CHECK();
    T* slots = checkpoints.as<T>();
    cuts = TileChunks<T>{choice + 2, 0, static_cast<int>(tiles), 0, slots,
                         slots + size_t(capacity) * kTilePixels, choice};
    if (capacity > 0) {
      back_checkpoint_kernel<T><<<static_cast<unsigned>(tiles + capacity), kTilePixels / 4, 0, stream>>>(
          p, visited, cuts);
      GSW_KERNEL_CHECK();
    }
  }
  // Whole tiles in one pass: in decreasing order of their visited splats (tile_order). A chunk's
  // tiles run in index order.
  const DeviceBuffer order_buf = tile_order(visited, ids, tiles, chunks.size() == 1 ? p.bins.M : 0, stream);
  const int32_t* order = chunks.size() == 1 ? order_buf.as<int32_t>() : nullptr;
  for (const auto& [c0, c1] : chunks) {
    const int t0 = static_cast<int>(c0), t1 = static_cast<int>(c1);
    layout.row0 = chunks.size() > 1 ? host[t0] : 0;  // the chunk's first row in the full layout
    if (choose) {  // returns at once unless cut
      TileChunks<T> part = cuts;
      part.t0 = t0;
      part.t1 = t1;
      backward_kernel<T, 4, false, true><<<static_cast<unsigned>(t1 - t0 + capacity), kTilePixels / 4, 0, stream>>>(
          p, g, layout, rec, TileSchedule{}, part);
      GSW_KERNEL_CHECK();
    }
    const unsigned chunk_grid = static_cast<unsigned>(t1 - t0);
    const TileSchedule sched{order, t0, choose ? choice : nullptr};
    if constexpr (kHasPx2) {
      if (px2 || choose) {
        backward_kernel<T, 2, false><<<chunk_grid, kTilePixels / 2, 0, stream>>>(p, g, layout, rec, sched,
                                                                                 TileChunks<T>{});
        GSW_KERNEL_CHECK();
      }
    }
    if (!px2) {
      backward_kernel<T, 4, false><<<chunk_grid, kTilePixels / 4, 0, stream>>>(p, g, layout, rec, sched,
                                                                               TileChunks<T>{});
      GSW_KERNEL_CHECK();
    }
    GSW_CUDA_CHECK(cudaMemsetAsync(big, 0, sizeof(int32_t), stream));
    if (chunks.size() == 1)
      reduce_blend_grads_kernel<T><<<blocks_for(p.N, kBlock), kBlock, 0, stream>>>(p, g, layout, rec, big);
    else  // the chunk's Gaussians only (a chunk of whole tiles holds at most budget_rows records)
      reduce_chunk_kernel<T><<<static_cast<unsigned>(8 * sms), kBlock, 0, stream>>>(p, g, layout, rec, big, t0, t1);
    GSW_KERNEL_CHECK();
    reduce_big_kernel<T><<<static_cast<unsigned>(8 * sms), kBlock, 0, stream>>>(p, g, layout, rec, big, t0, t1);
    GSW_KERNEL_CHECK();
  }
}

// The contribution's launches for C = CT channels (0: any). auto (the default): 4 pixels per thread,
// tiles in index order, those longer than a chunk cut into chunks (TileChunks) of
// chunk_size(M, wave) splats: no block walks much more than the mean share of one wave of blocks, so
// a few dense tiles no longer set the kernel's length. px4 / px2 (A/B benchmarks): whole tiles with
// that layout, densest first (tile_order; px2 only where its shared memory fits).
template <typename T, int CT>
void launch_contribution(const RasterParams<T>& p, const ContributionParams<T>& cp, Variant variant,
                         cudaStream_t stream) {
  const int64_t tiles = num_tiles(p);
  if (variant == Variant::kAuto) {
    const ChunkPlan<T> plan = plan_chunks<T>(
        p.bins.tile_offsets, tiles, p.bins.M,
        chunk_size(p.bins.M, wave_of(contribution_kernel<T, CT, 4>, kTilePixels / 4, device_sms())), stream);
    if (plan.extra > 0) {
      chunk_prefix_kernel<T><<<plan.grid, kTilePixels / 4, 0, stream>>>(p, plan.chunks);
      GSW_KERNEL_CHECK();
    }
    contribution_kernel<T, CT, 4><<<plan.grid, kTilePixels / 4, 0, stream>>>(p, cp, TileSchedule{}, plan.chunks);
    GSW_KERNEL_CHECK();
    return;
  }
  const unsigned grid = static_cast<unsigned>(tiles);
  DeviceBuffer buf(sizeof(int32_t) * size_t(2 * tiles));  // counts, ids
  int32_t* counts = buf.as<int32_t>();
  int32_t* ids = counts + tiles;
  tile_count_kernel<<<blocks_for(tiles, kBlock), kBlock, 0, stream>>>(p.bins.tile_offsets, static_cast<int>(tiles),
                                                                      counts, ids);
  GSW_KERNEL_CHECK();
  const DeviceBuffer order = tile_order(counts, ids, tiles, p.bins.M, stream);
  const TileSchedule sched{order.as<int32_t>(), 0, nullptr};
  if constexpr (contribution_shared_bytes<T, CT, 2>() <= 48 * 1024) {
    if (variant == Variant::kPx2) {
      contribution_kernel<T, CT, 2><<<grid, kTilePixels / 2, 0, stream>>>(p, cp, sched, TileChunks<T>{});
      GSW_KERNEL_CHECK();
      return;
    }
  }
  contribution_kernel<T, CT, 4><<<grid, kTilePixels / 4, 0, stream>>>(p, cp, sched, TileChunks<T>{});
  GSW_KERNEL_CHECK();
}

template <typename T>
void contribution(const RasterParams<T>& p, const ContributionParams<T>& cp) {
  cudaStream_t stream = current_stream();
  const Variant variant = layout_variant("GSW_CUDA_CONTRIBUTION", false);
  GSW_CUDA_CHECK(
      cudaMemsetAsync(cp.contribution, 0, size_t(p.N) * cp.C * sizeof(T), stream));
  GSW_CUDA_CHECK(cudaMemsetAsync(cp.hits, 0, size_t(p.N) * sizeof(int32_t), stream));
  GSW_CUDA_CHECK(cudaMemsetAsync(cp.max_weight, 0, size_t(p.N) * sizeof(T), stream));
  if (num_tiles(p) <= 0 || p.N <= 0 || p.bins.M <= 0) return;
  switch (cp.C) {
    case 1: launch_contribution<T, 1>(p, cp, variant, stream); break;
    case 3: launch_contribution<T, 3>(p, cp, variant, stream); break;
    default: launch_contribution<T, 0>(p, cp, variant, stream); break;
  }
}

template void rasterize_forward<float>(const RasterParams<float>&);
template void rasterize_forward<double>(const RasterParams<double>&);
template void rasterize_backward<float>(const RasterParams<float>&, const RasterGradParams<float>&, int64_t);
template void rasterize_backward<double>(const RasterParams<double>&, const RasterGradParams<double>&, int64_t);
template void contribution<float>(const RasterParams<float>&, const ContributionParams<float>&);
template void contribution<double>(const RasterParams<double>&,
                                   const ContributionParams<double>&);

}  // namespace gsw::cuda
