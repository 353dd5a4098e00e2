// CUDA blending stage: forward, backward and per-Gaussian contribution, one 16x16 thread block
// per tile, one thread per pixel.
//
// Forward and contribution share one front-to-back traversal (traverse_tile): the tile's splats
// are staged in shared memory in batches of 256, every thread walks the batch in order with the
// CPU backend's per-pixel decisions (splat_alpha, blend_terminates from core/math.h), a warp
// leaves a batch as soon as all its pixels have terminated and the block stops at the first batch
// where all of them have. The traversal hands each splat's blending weight w (0 if not blended)
// to a visitor: the forward accumulates colour/depth, the contribution reduces the weighted w
// and max w over the warp (one transposed butterfly for all values), adds them to the splat's
// shared-memory slot and, after each batch, adds the block's totals to
// the splat's outputs with one atomic per value.
//
// The backward walks each pixel back to front from its last blended splat (n_contrib), in
// batches from the tile's largest n_contrib down, recovering T_i = T_{i+1} / (1 - alpha_i) as the
// CPU backend does; the per-splat cotangents (splat_alpha_vjp) are summed over the warp with
// shuffles and then added with one atomic per warp and value, skipping warps where no pixel
// blended the splat.
#include "cuda/common.cuh"

namespace gsw::cuda {

namespace {

constexpr int kBlock = TILE_SIZE * TILE_SIZE;  // threads per tile = pixels per tile
constexpr int kBatch = kBlock;                 // splats staged per batch
static_assert(kBlock % 32 == 0, "a tile must hold whole warps");
constexpr int kVoteEvery = 8;  // splats between two "is the whole warp done?" votes

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

// The pixel of this thread.
struct PixelCtx {
  int tile;
  int px, py;
  bool inside;
  int64_t pix;
  int32_t start, end;  // the tile's range in the intersection list
};

template <typename T>
__device__ __forceinline__ PixelCtx pixel_ctx(const RasterParams<T>& p) {
  PixelCtx c;
  c.tile = blockIdx.x;
  const int tx = c.tile % p.bins.tiles_x, ty = c.tile / p.bins.tiles_x;
  c.px = tx * TILE_SIZE + static_cast<int>(threadIdx.x) % TILE_SIZE;
  c.py = ty * TILE_SIZE + static_cast<int>(threadIdx.x) / TILE_SIZE;
  c.inside = c.px < p.width && c.py < p.height;
  c.pix = int64_t(c.py) * p.width + c.px;
  c.start = p.bins.tile_offsets[c.tile];
  c.end = p.bins.tile_offsets[c.tile + 1];
  return c;
}

// Front-to-back traversal of this thread's tile (see the file comment). The visitor provides
//   load(slot, g):       stage extra per-splat data of Gaussian g in shared slot `slot`;
//   blend(slot, g, w):   called by every thread of a warp for each splat the warp visits, with
//                        this pixel's weight w = alpha T (0 when not blended);
//   end_batch(n):        called by every thread of the block after the n splats of a batch.
// On return `tr` is the final transmittance and `last` 1 + the tile-list index of the last
// blended splat (0 if none).
template <typename T, typename Visitor>
__device__ __forceinline__ void traverse_tile(const RasterParams<T>& p, const PixelCtx& c,
                                              Visitor& vis, T& tr, int32_t& last) {
  __shared__ SplatGeo<T> s_geo[kBatch];
  __shared__ int32_t s_id[kBatch];
  const T pxc = T(c.px) + T(0.5), pyc = T(c.py) + T(0.5);
  bool done = !c.inside;
  tr = T(1);
  last = 0;
  for (int32_t b = c.start; b < c.end; b += kBatch) {
    // Also the barrier before the shared batch is overwritten.
    if (__syncthreads_count(done) == kBlock) break;
    const int32_t idx = b + static_cast<int32_t>(threadIdx.x);
    if (idx < c.end) {
      const int32_t g = p.bins.gauss_ids[idx];
      s_id[threadIdx.x] = g;
      s_geo[threadIdx.x] = load_geo(p, g);
      vis.load(threadIdx.x, g);
    }
    __syncthreads();
    const int n = min(kBatch, c.end - b);
    // A warp leaves the batch once all its pixels are done (checked every kVoteEvery splats;
    // done pixels blend nothing, so when it is checked changes no result).
    for (int k = 0; k < n; ++k) {
      if ((k % kVoteEvery) == 0 && __all_sync(kFullMask, done)) break;
      T w = T(0);
      if (!done) {
        const T alpha = alpha_at(s_geo[k], pxc, pyc);
        if (alpha > T(0)) {
          if (blend_terminates(tr, alpha)) {
            done = true;  // this splat is not blended (INRIA)
          } else {
            w = alpha * tr;
            tr *= T(1) - alpha;
            last = b - c.start + k + 1;
          }
        }
      }
      vis.blend(k, s_id[k], w);
    }
    vis.end_batch(n);
  }
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
  __device__ __forceinline__ void blend(int slot, int32_t, T w) {
    if (w > T(0)) {
      const SplatColor<T> c = s_col[slot];
      r += w * c.r;
      g += w * c.g;
      b += w * c.b;
      d += w * c.depth;
    }
  }
};

template <typename T>
__global__ void __launch_bounds__(kBlock) forward_kernel(const RasterParams<T> p) {
  __shared__ SplatColor<T> s_col[kBatch];
  const PixelCtx c = pixel_ctx(p);
  ForwardVisitor<T> vis{p, s_col};
  T tr;
  int32_t last;
  traverse_tile(p, c, vis, tr, last);
  if (!c.inside) return;
  const int64_t P = int64_t(p.width) * p.height;
  p.image[c.pix] = vis.r + tr * p.background[0];
  p.image[P + c.pix] = vis.g + tr * p.background[1];
  p.image[2 * P + c.pix] = vis.b + tr * p.background[2];
  p.alpha[c.pix] = T(1) - tr;
  p.depth[c.pix] = vis.d;
  p.final_T[c.pix] = tr;
  p.n_contrib[c.pix] = last;
}

// ------------------------------------------------------------------ contribution

// Per-batch block accumulators of the contribution (CT > 0): each warp adds its warp-reduced sums
// to the splat's shared slot, and after the batch one thread per slot adds the block's totals to
// global memory, so a splat costs one set of global atomics per tile rather than per warp.
template <typename T, int CT>
struct ContributionShared {
  T sum[CT][kBatch];
  T max_w[kBatch];
  int32_t hits[kBatch];
  int32_t gid[kBatch];
};

// CT > 0: C = CT channels, this pixel's weights in registers, block accumulation in shared
// memory; CT = 0: any C, weights read from global memory, one atomic per warp and channel.
template <typename T, int CT>
struct ContributionVisitor {
  static_assert(CT == 0 || CT == 1 || CT == 3, "dispatched for C = 1, 3 or any (0)");
  const ContributionParams<T>& cp;
  int64_t P, pix;
  ContributionShared<T, (CT > 0 ? CT : 1)>* sh;
  T wreg[CT > 0 ? CT : 1];
  __device__ void load(int slot, int32_t gid) {
    if constexpr (CT > 0) {
#pragma unroll
      for (int ch = 0; ch < CT; ++ch) sh->sum[ch][slot] = T(0);
      sh->max_w[slot] = T(0);
      sh->hits[slot] = 0;
      sh->gid[slot] = gid;
    }
  }
  __device__ __forceinline__ void blend(int slot, int32_t gid, T w) {
    const bool hit = w > T(0);
    const unsigned ballot = __ballot_sync(kFullMask, hit);
    if (ballot == 0) return;  // warp-uniform
    const int lane = threadIdx.x & 31;
    if constexpr (CT == 3) {
      const T x = warp_sum3_max(w * wreg[0], w * wreg[1], w * wreg[2], w);
      if ((lane & 7) == 0) {
        const int q = lane >> 3;  // lanes 0, 8, 16: channel sums; lane 24: max
        if (q < 3)
          atomicAdd(&sh->sum[q][slot], x);
        else
          atomic_max_nonneg(&sh->max_w[slot], x);
      }
      if (lane == 0) atomicAdd(&sh->hits[slot], __popc(ballot));
    } else if constexpr (CT == 1) {
      const T x = warp_sum1_max(w * wreg[0], w);
      if (lane == 0) {
        atomicAdd(&sh->sum[0][slot], x);
        atomicAdd(&sh->hits[slot], __popc(ballot));
      } else if (lane == 16) {
        atomic_max_nonneg(&sh->max_w[slot], x);
      }
    } else {
      const int C = cp.C;
      T* out = cp.contribution + int64_t(C) * gid;
      for (int ch = 0; ch < C; ++ch) {
        const T v = warp_sum(hit ? w * cp.weights[ch * P + pix] : T(0));
        if (lane == 0 && v != T(0)) atomicAdd(out + ch, v);
      }
      const T m = warp_max(w);
      if (lane == 0) {
        atomicAdd(cp.hits + gid, __popc(ballot));
        atomic_max_nonneg(cp.max_weight + gid, m);
      }
    }
  }
  __device__ __forceinline__ void end_batch(int n) {
    if constexpr (CT > 0) {
      __syncthreads();  // every warp has finished the batch
      const int slot = threadIdx.x;
      if (slot < n && sh->hits[slot] > 0) {
        const int32_t gid = sh->gid[slot];
        T* out = cp.contribution + int64_t(CT) * gid;
#pragma unroll
        for (int ch = 0; ch < CT; ++ch)
          if (sh->sum[ch][slot] != T(0)) atomicAdd(out + ch, sh->sum[ch][slot]);
        atomicAdd(cp.hits + gid, sh->hits[slot]);
        atomic_max_nonneg(cp.max_weight + gid, sh->max_w[slot]);
      }
    }
  }
};

template <typename T, int CT>
__global__ void __launch_bounds__(kBlock)
    contribution_kernel(const RasterParams<T> p, const ContributionParams<T> cp) {
  __shared__ ContributionShared<T, (CT > 0 ? CT : 1)> sh;
  const PixelCtx c = pixel_ctx(p);
  const int64_t P = int64_t(p.width) * p.height;
  ContributionVisitor<T, CT> vis{cp, P, c.pix, &sh};
  if constexpr (CT > 0) {
#pragma unroll
    for (int ch = 0; ch < CT; ++ch) vis.wreg[ch] = c.inside ? cp.weights[ch * P + c.pix] : T(0);
  }
  T tr;
  int32_t last;
  traverse_tile(p, c, vis, tr, last);
}

// ------------------------------------------------------------------ backward

template <typename T>
__global__ void __launch_bounds__(kBlock)
    backward_kernel(const RasterParams<T> p, const RasterGradParams<T> g) {
  __shared__ SplatGeo<T> s_geo[kBatch];
  __shared__ SplatColor<T> s_col[kBatch];
  __shared__ int32_t s_id[kBatch];
  __shared__ int s_max_n;
  const PixelCtx c = pixel_ctx(p);
  const int64_t P = int64_t(p.width) * p.height;
  const T pxc = T(c.px) + T(0.5), pyc = T(c.py) + T(0.5);
  const int lane = threadIdx.x & 31;

  T tr = T(1), tf = T(1), vtf = T(0), vd = T(0);
  T vi[3] = {T(0), T(0), T(0)};
  int n_pix = 0;
  if (c.inside) {
    n_pix = p.n_contrib[c.pix];
    tr = tf = p.final_T[c.pix];
    for (int ch = 0; ch < 3; ++ch) vi[ch] = g.v_image[ch * P + c.pix];
    vd = g.v_depth ? g.v_depth[c.pix] : T(0);
    // d(loss)/d(T_final): background and the alpha output (alpha = 1 - T_final).
    vtf = vi[0] * p.background[0] + vi[1] * p.background[1] + vi[2] * p.background[2] -
          (g.v_alpha ? g.v_alpha[c.pix] : T(0));
  }
  // Colour and depth behind the current splat, per unit transmittance.
  T behind[3] = {T(0), T(0), T(0)}, behind_d = T(0);

  if (threadIdx.x == 0) s_max_n = 0;
  __syncthreads();
  const unsigned wmax = __reduce_max_sync(kFullMask, static_cast<unsigned>(n_pix));
  if (lane == 0 && wmax > 0) atomicMax(&s_max_n, static_cast<int>(wmax));
  __syncthreads();
  const int max_n = s_max_n;

  for (int hi = max_n; hi > 0; hi -= kBatch) {
    const int lo = hi > kBatch ? hi - kBatch : 0;
    __syncthreads();  // the previous batch is consumed
    if (lo + static_cast<int>(threadIdx.x) < hi) {
      const int32_t gid = p.bins.gauss_ids[c.start + lo + threadIdx.x];
      s_id[threadIdx.x] = gid;
      s_geo[threadIdx.x] = load_geo(p, gid);
      s_col[threadIdx.x] = {p.colors[3 * gid], p.colors[3 * gid + 1], p.colors[3 * gid + 2],
                            p.depths[gid]};
    }
    __syncthreads();
    for (int k = hi - lo - 1; k >= 0; --k) {
      const int j = lo + k;  // tile-local index
      const SplatGeo<T> s = s_geo[k];
      const T a = j < n_pix ? alpha_at(s, pxc, pyc) : T(0);
      const bool blended = a > T(0);
      if (!__any_sync(kFullMask, blended)) continue;  // warp-uniform
      T v[10];
#pragma unroll
      for (int q = 0; q < 10; ++q) v[q] = T(0);
      if (blended) {
        const SplatColor<T> col = s_col[k];
        const T om = T(1) - a;
        const T t = tr / om;  // transmittance in front of splat j
        tr = t;
        const T w = a * t;
        T v_alpha = t * ((col.r - behind[0]) * vi[0] + (col.g - behind[1]) * vi[1] +
                         (col.b - behind[2]) * vi[2] + (col.depth - behind_d) * vd) -
                    tf / om * vtf;
        const SplatGrad<T> sg = splat_alpha_vjp(Sym2<T>{s.ca, s.cb, s.cc}, s.mx, s.my, pxc, pyc,
                                                s.opacity, v_alpha);
        v[0] = sg.mean2d.x;
        v[1] = sg.mean2d.y;
        v[2] = sg.conic.a;
        v[3] = sg.conic.b;
        v[4] = sg.conic.c;
        v[5] = sg.opacity;
        v[6] = w * vi[0];
        v[7] = w * vi[1];
        v[8] = w * vi[2];
        v[9] = w * vd;
        behind[0] = a * col.r + om * behind[0];
        behind[1] = a * col.g + om * behind[1];
        behind[2] = a * col.b + om * behind[2];
        behind_d = a * col.depth + om * behind_d;
      }
#pragma unroll
      for (int q = 0; q < 10; ++q) v[q] = warp_sum(v[q]);
      if (lane == 0) {
        const int32_t gid = s_id[k];
        atomicAdd(g.v_means2d + 2 * gid, v[0]);
        atomicAdd(g.v_means2d + 2 * gid + 1, v[1]);
        atomicAdd(g.v_conics + 3 * gid, v[2]);
        atomicAdd(g.v_conics + 3 * gid + 1, v[3]);
        atomicAdd(g.v_conics + 3 * gid + 2, v[4]);
        atomicAdd(g.v_opacities + gid, v[5]);
        atomicAdd(g.v_colors + 3 * gid, v[6]);
        atomicAdd(g.v_colors + 3 * gid + 1, v[7]);
        atomicAdd(g.v_colors + 3 * gid + 2, v[8]);
        atomicAdd(g.v_depths + gid, v[9]);
      }
    }
  }
}

template <typename T>
int64_t num_tiles(const RasterParams<T>& p) {
  return int64_t(p.bins.tiles_x) * p.bins.tiles_y;
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
void rasterize_backward(const RasterParams<T>& p, const RasterGradParams<T>& g) {
  cudaStream_t stream = current_stream();
  const size_t n = size_t(p.N) * sizeof(T);
  GSW_CUDA_CHECK(cudaMemsetAsync(g.v_means2d, 0, 2 * n, stream));
  GSW_CUDA_CHECK(cudaMemsetAsync(g.v_conics, 0, 3 * n, stream));
  GSW_CUDA_CHECK(cudaMemsetAsync(g.v_colors, 0, 3 * n, stream));
  GSW_CUDA_CHECK(cudaMemsetAsync(g.v_opacities, 0, n, stream));
  GSW_CUDA_CHECK(cudaMemsetAsync(g.v_depths, 0, n, stream));
  const int64_t tiles = num_tiles(p);
  if (tiles <= 0 || p.N <= 0 || p.bins.M <= 0) return;
  backward_kernel<T><<<static_cast<unsigned>(tiles), kBlock, 0, stream>>>(p, g);
  GSW_KERNEL_CHECK();
}

template <typename T>
void contribution(const RasterParams<T>& p, const ContributionParams<T>& cp) {
  cudaStream_t stream = current_stream();
  GSW_CUDA_CHECK(
      cudaMemsetAsync(cp.contribution, 0, size_t(p.N) * cp.C * sizeof(T), stream));
  GSW_CUDA_CHECK(cudaMemsetAsync(cp.hits, 0, size_t(p.N) * sizeof(int32_t), stream));
  GSW_CUDA_CHECK(cudaMemsetAsync(cp.max_weight, 0, size_t(p.N) * sizeof(T), stream));
  const int64_t tiles = num_tiles(p);
  if (tiles <= 0 || p.N <= 0 || p.bins.M <= 0) return;
  const unsigned grid = static_cast<unsigned>(tiles);
  switch (cp.C) {
    case 1: contribution_kernel<T, 1><<<grid, kBlock, 0, stream>>>(p, cp); break;
    case 3: contribution_kernel<T, 3><<<grid, kBlock, 0, stream>>>(p, cp); break;
    default: contribution_kernel<T, 0><<<grid, kBlock, 0, stream>>>(p, cp); break;
  }
  GSW_KERNEL_CHECK();
}

template void rasterize_forward<float>(const RasterParams<float>&);
template void rasterize_forward<double>(const RasterParams<double>&);
template void rasterize_backward<float>(const RasterParams<float>&,
                                        const RasterGradParams<float>&);
template void rasterize_backward<double>(const RasterParams<double>&,
                                         const RasterGradParams<double>&);
template void contribution<float>(const RasterParams<float>&, const ContributionParams<float>&);
template void contribution<double>(const RasterParams<double>&,
                                   const ContributionParams<double>&);

}  // namespace gsw::cuda
