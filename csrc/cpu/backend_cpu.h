// CPU backend of the rasterizer ops. Templated on float / double; parallel over Gaussians or
// tiles on all of torch's intra-op threads. Every op is deterministic: no two threads ever
// write the same output element, and per-Gaussian reductions run in a fixed order.
#pragma once

#include <cstdint>
#include <vector>

#include "core/params.h"

namespace gsw::cpu {

template <typename T>
void project_forward(const ProjectParams<T>& p);
template <typename T>
void project_backward(const ProjectParams<T>& p, const ProjectGradParams<T>& g);

// The tiles of every Gaussian's tile_footprint (core/tiles.h), kept from count_tiles for
// fill_bins (each footprint is evaluated once): the Gaussians' tile ids row-major, in Gaussian
// order (that is, in entry order), split into the chunks the counting pass ran in.
struct TileLists {
  std::vector<std::vector<int32_t>> chunks;
};

// Number of tiles each Gaussian's tile_footprint holds (0 when culled), and their tile ids.
template <typename T>
void count_tiles(const BinParams<T>& p, int32_t* tiles_touched, TileLists& lists);
// Fill the bins from count_tiles' lists (consumed). `entry_offsets` must already hold the
// exclusive prefix sum of tiles_touched.
template <typename T>
void fill_bins(const BinParams<T>& p, TileLists& lists, int32_t* tile_offsets, int32_t* gauss_ids,
               const int32_t* entry_offsets, int32_t* entry_slots);

template <typename T>
void rasterize_forward(const RasterParams<T>& p);
// One record of kBlendGrads values (core/constants.h) per intersection, at most `budget_rows` of them
// at once (whole tiles per chunk; < 0: no limit; see BlendRecords in core/params.h).
template <typename T>
void rasterize_backward(const RasterParams<T>& p, const RasterGradParams<T>& g, int64_t budget_rows);
// `scratch` holds M * (C + 2) values.
template <typename T>
void contribution(const RasterParams<T>& p, const ContributionParams<T>& c, T* scratch);

}  // namespace gsw::cpu
