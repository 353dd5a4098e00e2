// The one pybind11 binding file of gsw: ops, constants and build information.
#include <torch/extension.h>

#include "core/constants.h"
#include "ops/ops.h"

#ifndef GSW_COMPILER
#define GSW_COMPILER "unknown"
#endif
#ifndef GSW_TORCH_VERSION
#define GSW_TORCH_VERSION "unknown"
#endif

// The torch version this module is compiled against, behind a marker that gsw/_ext.py finds in the
// file's bytes when the module cannot be loaded (a torch ABI mismatch fails before any code runs).
static const char kBuiltWithTorch[] = "gsw-built-with-torch=" GSW_TORCH_VERSION;

namespace py = pybind11;

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "gsw differentiable 3D Gaussian Splatting rasterizer (C++/CUDA kernels)";

  py::dict c;
  c["TILE_SIZE"] = gsw::TILE_SIZE;
  c["NEAR_PLANE"] = gsw::NEAR_PLANE;
  c["COV2D_DILATION"] = gsw::COV2D_DILATION;
  c["FRUSTUM_CLAMP"] = gsw::FRUSTUM_CLAMP;
  c["RADIUS_SIGMAS"] = gsw::RADIUS_SIGMAS;
  c["EIGEN_FLOOR"] = gsw::EIGEN_FLOOR;
  c["ALPHA_MAX"] = gsw::ALPHA_MAX;
  c["ALPHA_MIN"] = gsw::ALPHA_MIN;
  c["T_MIN"] = gsw::T_MIN;
  c["SKIP_LOG_MARGIN"] = gsw::SKIP_LOG_MARGIN;
  c["BIN_MARGIN"] = gsw::BIN_MARGIN;
  c["MAX_RADIUS"] = gsw::MAX_RADIUS;
  c["MAX_SH_DEGREE"] = gsw::MAX_SH_DEGREE;
  c["SH_COLOR_OFFSET"] = gsw::SH_COLOR_OFFSET;
  c["SH_C0"] = gsw::SH_C0;
  c["SH_C1"] = gsw::SH_C1;
  c["SH_C2"] = py::make_tuple(gsw::SH_C2_0, gsw::SH_C2_1, gsw::SH_C2_2, gsw::SH_C2_3, gsw::SH_C2_4);
  c["SH_C3"] = py::make_tuple(gsw::SH_C3_0, gsw::SH_C3_1, gsw::SH_C3_2, gsw::SH_C3_3,
                              gsw::SH_C3_4, gsw::SH_C3_5, gsw::SH_C3_6);
  c["BLEND_GRADS"] = gsw::kBlendGrads;
  c["RECORDS_BUDGET_MIB"] = gsw::kRecordsBudgetMiB;
  c["LAYOUT_CRITICAL_PATH_FACTOR"] = gsw::kCriticalPathFactor;
  c["LAYOUT_CUT_FACTOR"] = gsw::kCutFactor;
  py::list cuts;
  for (int l = 0; l < gsw::kNumCutLengths; ++l) cuts.append(gsw::cut_length(l));
  c["CUT_LENGTHS"] = py::tuple(cuts);
  m.attr("constants") = c;

  py::dict b;
  b["compiler"] = GSW_COMPILER;
  b["built_with_torch"] = kBuiltWithTorch + sizeof("gsw-built-with-torch=") - 1;
#ifdef _OPENMP
  b["openmp"] = true;
#else
  b["openmp"] = false;
#endif
#ifdef GSW_WITH_CUDA
  b["cuda"] = true;
  b["cuda_archs"] = GSW_CUDA_ARCHS;
#else
  b["cuda"] = false;
  b["cuda_archs"] = "";
#endif
  m.attr("build") = b;

  gsw::ops::register_ops(m);
}
