// gsw rasterizer constants: the ONLY place any threshold of the rasterizer is written.
// Shared unchanged by the CPU and CUDA backends and exposed to Python (gsw.constants).
// Values follow the INRIA 3DGS rasterizer (see ../shared/GUIDE.md, section 3).
#pragma once

namespace gsw {

// Tiles are TILE_SIZE x TILE_SIZE pixels.
constexpr int TILE_SIZE = 16;
// A Gaussian whose view-space depth is <= NEAR_PLANE is culled.
constexpr double NEAR_PLANE = 0.2;
// Added to the diagonal of the 2-D covariance (low-pass / anti-aliasing dilation).
constexpr double COV2D_DILATION = 0.3;
// The projected centre is clamped to +-FRUSTUM_CLAMP * tan(fov/2) before the EWA Jacobian.
constexpr double FRUSTUM_CLAMP = 1.3;
// Screen-space radius = ceil(RADIUS_SIGMAS * sqrt(largest eigenvalue)), or less for faint
// splats: as far as their alpha can reach ALPHA_MIN (footprint_radius in math.h).
constexpr double RADIUS_SIGMAS = 3.0;
// Upper bound of the pixel radius (keeps the int conversion defined for huge footprints).
constexpr int MAX_RADIUS = 1 << 30;
// Floor of (mid^2 - det) inside the eigenvalue square root.
constexpr double EIGEN_FLOOR = 0.1;
// Blending: alpha = min(ALPHA_MAX, opacity * G); contributions with alpha < ALPHA_MIN are skipped.
constexpr double ALPHA_MAX = 0.99;
constexpr double ALPHA_MIN = 1.0 / 255.0;
// A pixel stops when the next contribution would bring its transmittance below T_MIN
// (that contribution is not blended).
constexpr double T_MIN = 1e-4;
// Implementation margin (not a rendering threshold): a splat is skipped without evaluating
// exp(), or left out of a tile by the opacity-aware footprint, only when its exponent is below
// log(ALPHA_MIN / opacity) by more than this, so neither shortcut changes a result.
constexpr double SKIP_LOG_MARGIN = 1e-3;
// Implementation margin (pixels, not a rendering threshold) of the tile assignment's coordinates
// (tile_footprint in tiles.h), on top of its bounds of the rounding.
constexpr double BIN_MARGIN = 1e-2;
// Largest supported spherical-harmonics degree.
constexpr int MAX_SH_DEGREE = 3;

// Real spherical-harmonics basis constants (degree 0..3), INRIA ordering.
constexpr double SH_C0 = 0.28209479177387814;
constexpr double SH_C1 = 0.4886025119029199;
constexpr double SH_C2_0 = 1.0925484305920792;
constexpr double SH_C2_1 = -1.0925484305920792;
constexpr double SH_C2_2 = 0.31539156525252005;
constexpr double SH_C2_3 = -1.0925484305920792;
constexpr double SH_C2_4 = 0.5462742152960396;
constexpr double SH_C3_0 = -0.5900435899266435;
constexpr double SH_C3_1 = 2.890611442640554;
constexpr double SH_C3_2 = -0.4570457994644658;
constexpr double SH_C3_3 = 0.3731763325901154;
constexpr double SH_C3_4 = -0.4570457994644658;
constexpr double SH_C3_5 = 1.445305721320277;
constexpr double SH_C3_6 = -0.5900435899266435;
// Colour offset added after SH evaluation (INRIA: rgb = SH(dir) + 0.5, clamped at 0).
constexpr double SH_COLOR_OFFSET = 0.5;

// Layout, not a threshold: a splat's blend cotangents as one record (CPU scratch rows, CUDA warp
// sums), in this order: mean2d x, y; conic a, b, c; opacity; colour r, g, b; depth.
constexpr int kBlendGrads = 10;
// Scheduling thresholds of the CUDA blend backward (rasterize_cuda.cu, choose_layout_kernel), not
// rendering thresholds: they choose a layout per render, and the layouts agree to rounding.
// A render's densest tile sets the kernel's length when its walk is more than
// kCriticalPathFactor times the busy tiles' mean share of one wave of 4-pixel blocks (BENCHMARKS.md
// 2k / 2l: a trained model's densest tiles visit 6-7x the mean); the backward then walks whole
// tiles with 2 pixels per thread, otherwise with 4 (fewer warps, each reading a splat for more
// pixels: the higher throughput). The contribution cuts tiles longer than its chunk into chunks on
// every render.
constexpr int kCriticalPathFactor = 2;
// Such a render's tiles are cut into chunks when the densest tile's walk is more than kCutFactor
// times that share (BENCHMARKS.md 2s, the blend backward on a lego model, one wave of 8 blocks per
// SM: at 3.9x the share (1600x1600) cut 0.68-0.71 ms, whole tiles with 2 pixels per thread
// 0.64-0.66; at 11.6x (800x800) 0.44-0.50 against 0.85; at 30x (400x400) 0.37 against 1.30).
constexpr int kCutFactor = 6;
// The shortest chunk such a render's tiles are cut at (splats, a multiple of the 4-pixel batch of
// 64); the longer ones are 1.5x and 2x the one before: 128, 192, 256, 384, ... 2048, kNumCutLengths
// in all, cut_length(0) shortest (BENCHMARKS.md 2s: 128 was the fastest of 128 / 256 / ~450 on lego
// at 800x800).
constexpr int kCutLengthMin = 128;
constexpr int kNumCutLengths = 9;
constexpr int cut_length(int l) { return (l % 2 != 0 ? kCutLengthMin * 3 / 2 : kCutLengthMin) << (l / 2); }

// Default budget of the blend backward's records held at once (MiB; core/params.h
// blend_records_budget): a cap against running out of memory on very large renders.
constexpr double kRecordsBudgetMiB = 256.0;

}  // namespace gsw
