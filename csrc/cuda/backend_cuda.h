// CUDA backend of the rasterizer ops. Same parameter structs and the same math/constants
// headers (core/*.h) as the CPU backend; templated on float / double (float32 is the fast path,
// float64 exists for parity tests).
//
// Every function enqueues its kernels on torch's current CUDA stream of the current device (the
// dispatcher sets the device from the tensors) and returns without synchronising. Temporary
// buffers come from torch's caching allocator.
//
// Differences from the CPU backend (results agree to rounding):
//  * binning sorts the Gaussians by depth and then their intersections by tile with cub's device
//    radix sort (both stable, so equal depths keep the Gaussian index order: the CPU's bins);
//    `fill_bins` needs the number of intersections M (the dispatcher knows it);
//  * rasterize_backward reduces each splat's ten cotangents over a warp (shuffles) and over the
//    tile's warps (shared memory), stores one record per visited intersection and sums them per
//    Gaussian in intersection order, as the CPU does (bitwise deterministic, not bitwise equal to
//    the CPU: the sums within a tile are grouped differently); its record buffer (torch's
//    allocator) is sized for all M intersections up to 64 MiB (no synchronisation), else, after
//    one host synchronisation, for the visited ones, in chunks of whole tiles when those exceed the
//    records budget (core/params.h BlendRecords);
//  * contribution adds its per-tile totals to the per-Gaussian outputs with atomics (one per tile,
//    after summing the warps in shared memory, except the channel sums for C other than 1 or 3:
//    one per warp): the float sums' order is not fixed (hits and max_weight are exact);
//  * entry_slots are filled exactly as on the CPU (the backward's reduction reads them).
#pragma once

#include <cstdint>

#include "core/params.h"

namespace gsw::cuda {

template <typename T>
void project_forward(const ProjectParams<T>& p);
template <typename T>
void project_backward(const ProjectParams<T>& p, const ProjectGradParams<T>& g);

// Number of tiles each Gaussian's tile_footprint (core/tiles.h) holds (0 when culled).
template <typename T>
void count_tiles(const BinParams<T>& p, int32_t* tiles_touched);
// Fill the bins; `entry_offsets` must already hold the exclusive prefix sum of tiles_touched
// (on the device) and M = entry_offsets[N] (on the host).
template <typename T>
void fill_bins(const BinParams<T>& p, int32_t* tile_offsets, int32_t* gauss_ids,
               const int32_t* entry_offsets, int32_t* entry_slots, int64_t M);

template <typename T>
void rasterize_forward(const RasterParams<T>& p);
// Outputs of `g` need no initialisation. At most `budget_rows` records at once (< 0: no limit).
template <typename T>
void rasterize_backward(const RasterParams<T>& p, const RasterGradParams<T>& g, int64_t budget_rows);
template <typename T>
void contribution(const RasterParams<T>& p, const ContributionParams<T>& c);

}  // namespace gsw::cuda
