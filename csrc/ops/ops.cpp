// Dispatchers of the rasterizer ops: check inputs (naming the offending argument), allocate
// outputs, fill the parameter structs and call the CPU or CUDA backend.
#include "ops/ops.h"

#include <cmath>
#include <cstdlib>
#include <string>
#include <tuple>
#include <utility>

#include "core/project.h"
#include "cpu/backend_cpu.h"
#ifdef GSW_WITH_CUDA
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include "cuda/backend_cuda.h"
#endif

namespace gsw::ops {

namespace py = pybind11;
using torch::Tensor;

namespace {

// ------------------------------------------------------------------ argument checks

#define GSW_CHECK_ARG(cond, name, ...) \
  TORCH_CHECK(cond, "gsw: argument '", name, "': ", __VA_ARGS__)

std::string shape_str(const Tensor& t) {
  std::string s = "[";
  for (int64_t d = 0; d < t.dim(); ++d) s += (d ? ", " : "") + std::to_string(t.size(d));
  return s + "]";
}

// Checks device, dtype, contiguity and shape; -1 in `shape` matches any size.
void check_tensor(const Tensor& t, const char* name, const Tensor& like,
                  std::initializer_list<int64_t> shape) {
  GSW_CHECK_ARG(t.defined(), name, "is undefined");
  GSW_CHECK_ARG(t.device() == like.device(), name, "is on ", t.device(), " but expected ",
                like.device());
  GSW_CHECK_ARG(t.scalar_type() == like.scalar_type(), name, "has dtype ", t.scalar_type(),
                " but expected ", like.scalar_type());
  GSW_CHECK_ARG(t.is_contiguous(), name, "must be contiguous");
  bool ok = t.dim() == static_cast<int64_t>(shape.size());
  int64_t d = 0;
  for (int64_t s : shape) {
    if (!ok) break;
    ok = (s < 0 || t.size(d) == s);
    ++d;
  }
  std::string want = "[";
  d = 0;
  for (int64_t s : shape) want += (d++ ? ", " : "") + (s < 0 ? std::string("*") : std::to_string(s));
  GSW_CHECK_ARG(ok, name, "has shape ", shape_str(t), " but expected ", want + "]");
}

void check_int_tensor(const Tensor& t, const char* name, const Tensor& like, int64_t numel) {
  GSW_CHECK_ARG(t.defined() && t.scalar_type() == torch::kInt32, name, "must be an int32 tensor");
  GSW_CHECK_ARG(t.device() == like.device(), name, "is on ", t.device(), " but expected ",
                like.device());
  GSW_CHECK_ARG(t.is_contiguous(), name, "must be contiguous");
  GSW_CHECK_ARG(numel < 0 || t.numel() == numel, name, "has ", t.numel(), " elements, expected ",
                numel);
}

void check_float(const Tensor& t, const char* name) {
  GSW_CHECK_ARG(t.scalar_type() == torch::kFloat32 || t.scalar_type() == torch::kFloat64, name,
                "must be float32 or float64, got ", t.scalar_type());
}

[[noreturn]] void no_cuda() {
  TORCH_CHECK(false,
              "gsw was built without CUDA: CUDA tensors are not supported by this build. "
              "Rebuild on a machine with nvcc and a CUDA-enabled torch (see README), or move "
              "the tensors to the CPU.");
}

int tiles_along(int size) { return (size + TILE_SIZE - 1) / TILE_SIZE; }

// ------------------------------------------------------------------ camera

struct CameraArgs {
  Tensor viewmat;  // [4, 4] world-to-camera, any float dtype / device
  double fx, fy, cx, cy;
  int width, height;
};

void check_camera(const CameraArgs& c) {
  GSW_CHECK_ARG(c.viewmat.dim() == 2 && c.viewmat.size(0) == 4 && c.viewmat.size(1) == 4,
                "viewmat", "has shape ", shape_str(c.viewmat), " but expected [4, 4]");
  GSW_CHECK_ARG(c.width > 0 && c.height > 0, "width/height", "must be positive, got ", c.width,
                "x", c.height);
  GSW_CHECK_ARG(std::isfinite(c.fx) && std::isfinite(c.fy) && c.fx > 0 && c.fy > 0, "fx/fy",
                "must be finite and positive, got ", c.fx, ", ", c.fy);
  GSW_CHECK_ARG(std::isfinite(c.cx) && std::isfinite(c.cy), "cx/cy", "must be finite");
}

template <typename T>
Camera<T> to_camera(const CameraArgs& c) {
  const Tensor v = c.viewmat.detach().to(torch::kCPU, torch::kFloat64).contiguous();
  const double* m = v.data_ptr<double>();
  Camera<T> cam;
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) cam.R.m[r][k] = static_cast<T>(m[4 * r + k]);
  cam.t = {static_cast<T>(m[3]), static_cast<T>(m[7]), static_cast<T>(m[11])};
  cam.fx = static_cast<T>(c.fx);
  cam.fy = static_cast<T>(c.fy);
  cam.cx = static_cast<T>(c.cx);
  cam.cy = static_cast<T>(c.cy);
  cam.width = c.width;
  cam.height = c.height;
  return cam;
}

// ------------------------------------------------------------------ projection

struct GaussianArgs {
  Tensor means, quats, log_scales, opacity_logits, sh;
  int sh_degree;
};

int check_gaussians(const GaussianArgs& g) {
  check_float(g.means, "means");
  const int64_t N = g.means.size(0);
  check_tensor(g.means, "means", g.means, {N, 3});
  check_tensor(g.quats, "quats", g.means, {N, 4});
  check_tensor(g.log_scales, "log_scales", g.means, {N, 3});
  check_tensor(g.opacity_logits, "opacity_logits", g.means, {N});
  GSW_CHECK_ARG(g.sh_degree >= -1 && g.sh_degree <= MAX_SH_DEGREE, "sh_degree",
                "must be in [-1, ", MAX_SH_DEGREE, "], got ", g.sh_degree);
  if (g.sh_degree < 0) {
    check_tensor(g.sh, "colors", g.means, {N, 3});
    return 0;
  }
  check_tensor(g.sh, "sh", g.means, {N, -1, 3});
  const int K = static_cast<int>(g.sh.size(1));
  GSW_CHECK_ARG(K >= sh_num_coeffs(g.sh_degree), "sh", "has ", K,
                " coefficients per Gaussian, degree ", g.sh_degree, " needs ",
                sh_num_coeffs(g.sh_degree));
  return K;
}

template <typename T>
ProjectParams<T> project_params(const GaussianArgs& g, const CameraArgs& c, int K) {
  ProjectParams<T> p;
  p.N = static_cast<int>(g.means.size(0));
  p.K = K;
  p.sh_degree = g.sh_degree;
  p.cam = to_camera<T>(c);
  p.means = g.means.data_ptr<T>();
  p.quats = g.quats.data_ptr<T>();
  p.log_scales = g.log_scales.data_ptr<T>();
  p.opacity_logits = g.opacity_logits.data_ptr<T>();
  p.sh = g.sh.data_ptr<T>();
  return p;
}

py::tuple project_forward(const Tensor& means, const Tensor& quats, const Tensor& log_scales,
                          const Tensor& opacity_logits, const Tensor& sh, int sh_degree,
                          const Tensor& viewmat, double fx, double fy, double cx, double cy,
                          int width, int height, const c10::optional<Tensor>& nonfinite) {
  const GaussianArgs g{means, quats, log_scales, opacity_logits, sh, sh_degree};
  const CameraArgs c{viewmat, fx, fy, cx, cy, width, height};
  const int K = check_gaussians(g);
  check_camera(c);
  if (nonfinite) check_int_tensor(*nonfinite, "nonfinite", means, 1);
  const int64_t N = means.size(0);
  auto opts = means.options();
  Tensor radii = torch::empty({N}, opts.dtype(torch::kInt32));
  Tensor means2d = torch::empty({N, 2}, opts), conics = torch::empty({N, 3}, opts);
  Tensor depths = torch::empty({N}, opts), colors = torch::empty({N, 3}, opts);
  Tensor opacities = torch::empty({N}, opts);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "gsw_project_forward", [&] {
    ProjectParams<scalar_t> p = project_params<scalar_t>(g, c, K);
    p.radii = radii.data_ptr<int32_t>();
    p.means2d = means2d.data_ptr<scalar_t>();
    p.conics = conics.data_ptr<scalar_t>();
    p.depths = depths.data_ptr<scalar_t>();
    p.colors = colors.data_ptr<scalar_t>();
    p.opacities = opacities.data_ptr<scalar_t>();
    if (nonfinite) p.nonfinite = nonfinite->data_ptr<int32_t>();
    if (means.is_cuda()) {
#ifdef GSW_WITH_CUDA
      const c10::cuda::CUDAGuard guard(means.device());
      cuda::project_forward(p);
#else
      no_cuda();
#endif
    } else {
      cpu::project_forward(p);
    }
  });
  return py::make_tuple(radii, means2d, conics, depths, colors, opacities);
}

py::tuple project_backward(const Tensor& means, const Tensor& quats, const Tensor& log_scales,
                           const Tensor& opacity_logits, const Tensor& sh, int sh_degree,
                           const Tensor& viewmat, double fx, double fy, double cx, double cy,
                           int width, int height, const Tensor& radii, const Tensor& v_means2d,
                           const Tensor& v_conics, const Tensor& v_depths, const Tensor& v_colors,
                           const Tensor& v_opacities) {
  const GaussianArgs g{means, quats, log_scales, opacity_logits, sh, sh_degree};
  const CameraArgs c{viewmat, fx, fy, cx, cy, width, height};
  const int K = check_gaussians(g);
  check_camera(c);
  const int64_t N = means.size(0);
  check_int_tensor(radii, "radii", means, N);
  check_tensor(v_means2d, "v_means2d", means, {N, 2});
  check_tensor(v_conics, "v_conics", means, {N, 3});
  check_tensor(v_depths, "v_depths", means, {N});
  check_tensor(v_colors, "v_colors", means, {N, 3});
  check_tensor(v_opacities, "v_opacities", means, {N});
  Tensor v_means = torch::empty_like(means), v_quats = torch::empty_like(quats);
  Tensor v_log_scales = torch::empty_like(log_scales);
  Tensor v_opacity_logits = torch::empty_like(opacity_logits), v_sh = torch::empty_like(sh);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "gsw_project_backward", [&] {
    ProjectParams<scalar_t> p = project_params<scalar_t>(g, c, K);
    p.radii = radii.data_ptr<int32_t>();
    ProjectGradParams<scalar_t> gp;
    gp.v_means2d = v_means2d.data_ptr<scalar_t>();
    gp.v_conics = v_conics.data_ptr<scalar_t>();
    gp.v_depths = v_depths.data_ptr<scalar_t>();
    gp.v_colors = v_colors.data_ptr<scalar_t>();
    gp.v_opacities = v_opacities.data_ptr<scalar_t>();
    gp.v_means = v_means.data_ptr<scalar_t>();
    gp.v_quats = v_quats.data_ptr<scalar_t>();
    gp.v_log_scales = v_log_scales.data_ptr<scalar_t>();
    gp.v_opacity_logits = v_opacity_logits.data_ptr<scalar_t>();
    gp.v_sh = v_sh.data_ptr<scalar_t>();
    if (means.is_cuda()) {
#ifdef GSW_WITH_CUDA
      const c10::cuda::CUDAGuard guard(means.device());
      cuda::project_backward(p, gp);
#else
      no_cuda();
#endif
    } else {
      cpu::project_backward(p, gp);
    }
  });
  return py::make_tuple(v_means, v_quats, v_log_scales, v_opacity_logits, v_sh);
}

// ------------------------------------------------------------------ binning

// Tile bins as tensors (see gsw::TileBins).
struct Bins {
  int tiles_x = 0, tiles_y = 0;
  Tensor tile_offsets, gauss_ids, entry_offsets, entry_slots;
  int32_t nonfinite = 0;  // host copy of the projection's nonfinite flags (0 when not given)

  TileBins view() const {
    TileBins b;
    b.tiles_x = tiles_x;
    b.tiles_y = tiles_y;
    b.M = gauss_ids.numel();
    b.tile_offsets = tile_offsets.data_ptr<int32_t>();
    b.gauss_ids = gauss_ids.data_ptr<int32_t>();
    b.entry_offsets = entry_offsets.data_ptr<int32_t>();
    b.entry_slots = entry_slots.data_ptr<int32_t>();
    return b;
  }
};

// Host values of the intersection count (the last inclusive prefix sum `cum[N - 1]`) and of the
// optional nonfinite flags. This is the binning's one host synchronisation (the outputs' sizes
// depend on M); the flags travel with it, so validation adds no synchronisation of its own.
std::pair<int64_t, int32_t> read_count_and_flags(const Tensor& cum, const c10::optional<Tensor>& nonfinite) {
  const int64_t N = cum.size(0);
  if (N == 0) return {0, 0};
  if (!cum.is_cuda()) return {cum[N - 1].item<int64_t>(), nonfinite ? nonfinite->item<int32_t>() : 0};
#ifdef GSW_WITH_CUDA
  auto pinned = [](c10::ScalarType t) {
    return torch::empty({1}, torch::TensorOptions().dtype(t).pinned_memory(true));
  };
  Tensor m = pinned(torch::kInt64), f = pinned(torch::kInt32);
  m.copy_(cum.slice(0, N - 1, N), /*non_blocking=*/true);
  if (nonfinite) f.copy_(*nonfinite, /*non_blocking=*/true);
  c10::cuda::getCurrentCUDAStream(cum.get_device()).synchronize();
  return {m.data_ptr<int64_t>()[0], nonfinite ? f.data_ptr<int32_t>()[0] : 0};
#else
  no_cuda();
#endif
}

Bins bin_gaussians(const Tensor& means2d, const Tensor& conics, const Tensor& opacities,
                   const Tensor& radii, const Tensor& depths, int width, int height,
                   const c10::optional<Tensor>& nonfinite) {
  check_float(means2d, "means2d");
  const int64_t N = means2d.size(0);
  check_tensor(means2d, "means2d", means2d, {N, 2});
  check_tensor(conics, "conics", means2d, {N, 3});
  check_tensor(opacities, "opacities", means2d, {N});
  check_int_tensor(radii, "radii", means2d, N);
  check_tensor(depths, "depths", means2d, {N});
  if (nonfinite) check_int_tensor(*nonfinite, "nonfinite", means2d, 1);
  GSW_CHECK_ARG(width > 0 && height > 0, "width/height", "must be positive");
  Bins b;
  b.tiles_x = tiles_along(width);
  b.tiles_y = tiles_along(height);
  const int64_t num_tiles = int64_t(b.tiles_x) * b.tiles_y;
  auto iopts = means2d.options().dtype(torch::kInt32);
  Tensor touched = torch::empty({N}, iopts);
  const bool on_cuda = means2d.is_cuda();
#ifdef GSW_WITH_CUDA
  c10::cuda::OptionalCUDAGuard guard;
  if (on_cuda) guard.set_device(means2d.device());
#else
  if (on_cuda) no_cuda();
#endif
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "gsw_count_tiles", [&] {
    BinParams<scalar_t> p;
    p.N = static_cast<int>(N);
    p.tiles_x = b.tiles_x;
    p.tiles_y = b.tiles_y;
    p.means2d = means2d.data_ptr<scalar_t>();
    p.conics = conics.data_ptr<scalar_t>();
    p.opacities = opacities.data_ptr<scalar_t>();
    p.radii = radii.data_ptr<int32_t>();
    p.depths = depths.data_ptr<scalar_t>();
#ifdef GSW_WITH_CUDA
    if (on_cuda) cuda::count_tiles(p, touched.data_ptr<int32_t>());
#endif
    cpu::TileLists lists;
    if (!on_cuda) cpu::count_tiles(p, touched.data_ptr<int32_t>(), lists);
    // entry_offsets = exclusive prefix sum (int64 to detect overflow of the int32 index space).
    Tensor cum = torch::cumsum(touched, 0, torch::kInt64);
    int64_t M;
    std::tie(M, b.nonfinite) = read_count_and_flags(cum, nonfinite);
    TORCH_CHECK(M < (int64_t(1) << 31), "gsw: too many tile intersections (", M,
                ") for int32 indices; render at a lower resolution or with fewer Gaussians");
    b.entry_offsets = torch::zeros({N + 1}, iopts);
    if (N > 0) b.entry_offsets.slice(0, 1).copy_(cum);
    b.tile_offsets = torch::empty({num_tiles + 1}, iopts);
    b.gauss_ids = torch::empty({M}, iopts);
    b.entry_slots = torch::empty({M}, iopts);
    int32_t* tile_offsets = b.tile_offsets.data_ptr<int32_t>();
    int32_t* gauss_ids = b.gauss_ids.data_ptr<int32_t>();
    const int32_t* entry_offsets = b.entry_offsets.data_ptr<int32_t>();
    int32_t* entry_slots = b.entry_slots.data_ptr<int32_t>();
#ifdef GSW_WITH_CUDA
    if (on_cuda) cuda::fill_bins(p, tile_offsets, gauss_ids, entry_offsets, entry_slots, M);
#endif
    if (!on_cuda) cpu::fill_bins(p, lists, tile_offsets, gauss_ids, entry_offsets, entry_slots);
  });
  return b;
}

// A binning made earlier, from its tensors (e.g. those a render saved for its backward): checks
// that they are one consistent binning for the image size, copies nothing.
Bins bins_from_tensors(const Tensor& tile_offsets, const Tensor& gauss_ids, const Tensor& entry_offsets,
                       const Tensor& entry_slots, int width, int height) {
  GSW_CHECK_ARG(width > 0 && height > 0, "width/height", "must be positive");
  Bins b;
  b.tiles_x = tiles_along(width);
  b.tiles_y = tiles_along(height);
  check_int_tensor(tile_offsets, "tile_offsets", tile_offsets, int64_t(b.tiles_x) * b.tiles_y + 1);
  check_int_tensor(gauss_ids, "gauss_ids", tile_offsets, -1);
  check_int_tensor(entry_offsets, "entry_offsets", tile_offsets, -1);
  GSW_CHECK_ARG(entry_offsets.numel() >= 1, "entry_offsets", "must hold N + 1 >= 1 elements");
  check_int_tensor(entry_slots, "entry_slots", tile_offsets, gauss_ids.numel());
  b.tile_offsets = tile_offsets;
  b.gauss_ids = gauss_ids;
  b.entry_offsets = entry_offsets;
  b.entry_slots = entry_slots;
  return b;
}

// ------------------------------------------------------------------ blending

struct SplatArgs {
  Tensor means2d, conics, colors, opacities, depths;
};

template <typename T>
RasterParams<T> raster_params(const SplatArgs& s, const Bins& bins, int width, int height,
                              const Tensor* background) {
  RasterParams<T> p;
  p.N = static_cast<int>(s.means2d.size(0));
  p.width = width;
  p.height = height;
  p.bins = bins.view();
  p.means2d = s.means2d.data_ptr<T>();
  p.conics = s.conics.data_ptr<T>();
  p.opacities = s.opacities.data_ptr<T>();
  if (s.colors.defined()) p.colors = s.colors.data_ptr<T>();
  if (s.depths.defined()) p.depths = s.depths.data_ptr<T>();
  if (background) p.background = background->data_ptr<T>();
  return p;
}

void check_splats(const SplatArgs& s, const Bins& bins, int width, int height, bool need_color) {
  check_float(s.means2d, "means2d");
  const int64_t N = s.means2d.size(0);
  check_tensor(s.means2d, "means2d", s.means2d, {N, 2});
  check_tensor(s.conics, "conics", s.means2d, {N, 3});
  check_tensor(s.opacities, "opacities", s.means2d, {N});
  if (need_color) {
    check_tensor(s.colors, "colors", s.means2d, {N, 3});
    check_tensor(s.depths, "depths", s.means2d, {N});
  }
  GSW_CHECK_ARG(bins.tiles_x == tiles_along(width) && bins.tiles_y == tiles_along(height), "bins",
                "were built for another image size");
  check_int_tensor(bins.entry_offsets, "bins.entry_offsets", s.means2d, N + 1);
  check_int_tensor(bins.tile_offsets, "bins.tile_offsets", s.means2d,
                   int64_t(bins.tiles_x) * bins.tiles_y + 1);
}

py::tuple rasterize_forward(const Tensor& means2d, const Tensor& conics, const Tensor& colors,
                            const Tensor& opacities, const Tensor& depths,
                            const Tensor& background, const Bins& bins, int width, int height) {
  const SplatArgs s{means2d, conics, colors, opacities, depths};
  check_splats(s, bins, width, height, true);
  check_tensor(background, "background", means2d, {3});
  auto opts = means2d.options();
  Tensor image = torch::empty({3, height, width}, opts);
  Tensor alpha = torch::empty({1, height, width}, opts);
  Tensor depth = torch::empty({1, height, width}, opts);
  Tensor final_T = torch::empty({height, width}, opts);
  Tensor n_contrib = torch::empty({height, width}, opts.dtype(torch::kInt32));
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "gsw_rasterize_forward", [&] {
    RasterParams<scalar_t> p = raster_params<scalar_t>(s, bins, width, height, &background);
    p.image = image.data_ptr<scalar_t>();
    p.alpha = alpha.data_ptr<scalar_t>();
    p.depth = depth.data_ptr<scalar_t>();
    p.final_T = final_T.data_ptr<scalar_t>();
    p.n_contrib = n_contrib.data_ptr<int32_t>();
    if (means2d.is_cuda()) {
#ifdef GSW_WITH_CUDA
      const c10::cuda::CUDAGuard guard(means2d.device());
      cuda::rasterize_forward(p);
#else
      no_cuda();
#endif
    } else {
      cpu::rasterize_forward(p);
    }
  });
  return py::make_tuple(image, alpha, depth, final_T, n_contrib);
}

// The blend backward's record budget (core/params.h blend_records_budget): the default, or the
// GSW_BLEND_RECORDS_MIB setting (read at every call; 0: no limit).
int64_t records_budget_rows(int value_bytes) {
  const char* e = std::getenv("GSW_BLEND_RECORDS_MIB");
  if (e == nullptr || *e == '\0') return blend_records_budget(value_bytes);
  char* end = nullptr;
  const double mib = std::strtod(e, &end);
  TORCH_CHECK(end != e && *end == '\0' && mib >= 0.0 && std::isfinite(mib),
              "gsw: GSW_BLEND_RECORDS_MIB must be a number of MiB >= 0 (0: no limit), not '", e, "'");
  return blend_records_budget(value_bytes, mib);
}

py::tuple rasterize_backward(const Tensor& means2d, const Tensor& conics, const Tensor& colors,
                             const Tensor& opacities, const Tensor& depths,
                             const Tensor& background, const Bins& bins, int width, int height,
                             const Tensor& final_T, const Tensor& n_contrib, const Tensor& v_image,
                             const c10::optional<Tensor>& v_alpha,
                             const c10::optional<Tensor>& v_depth) {
  const SplatArgs s{means2d, conics, colors, opacities, depths};
  check_splats(s, bins, width, height, true);
  check_tensor(background, "background", means2d, {3});
  check_tensor(final_T, "final_T", means2d, {height, width});
  check_int_tensor(n_contrib, "n_contrib", means2d, int64_t(height) * width);
  check_tensor(v_image, "v_image", means2d, {3, height, width});
  if (v_alpha) check_tensor(*v_alpha, "v_alpha", means2d, {1, height, width});
  if (v_depth) check_tensor(*v_depth, "v_depth", means2d, {1, height, width});
  Tensor v_means2d = torch::empty_like(means2d), v_conics = torch::empty_like(conics);
  Tensor v_colors = torch::empty_like(colors), v_opacities = torch::empty_like(opacities);
  Tensor v_depths = torch::empty_like(depths);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "gsw_rasterize_backward", [&] {
    RasterParams<scalar_t> p = raster_params<scalar_t>(s, bins, width, height, &background);
    p.final_T = final_T.data_ptr<scalar_t>();
    p.n_contrib = n_contrib.data_ptr<int32_t>();
    RasterGradParams<scalar_t> g;
    g.v_image = v_image.data_ptr<scalar_t>();
    g.v_alpha = v_alpha ? v_alpha->data_ptr<scalar_t>() : nullptr;
    g.v_depth = v_depth ? v_depth->data_ptr<scalar_t>() : nullptr;
    g.v_means2d = v_means2d.data_ptr<scalar_t>();
    g.v_conics = v_conics.data_ptr<scalar_t>();
    g.v_colors = v_colors.data_ptr<scalar_t>();
    g.v_opacities = v_opacities.data_ptr<scalar_t>();
    g.v_depths = v_depths.data_ptr<scalar_t>();
    const int64_t budget = records_budget_rows(sizeof(scalar_t));
    if (means2d.is_cuda()) {
#ifdef GSW_WITH_CUDA
      const c10::cuda::CUDAGuard guard(means2d.device());
      cuda::rasterize_backward(p, g, budget);
#else
      no_cuda();
#endif
    } else {
      cpu::rasterize_backward(p, g, budget);
    }
  });
  return py::make_tuple(v_means2d, v_conics, v_colors, v_opacities, v_depths);
}

py::tuple contribution(const Tensor& means2d, const Tensor& conics, const Tensor& opacities,
                       const Bins& bins, int width, int height, const Tensor& weights) {
  const SplatArgs s{means2d, conics, Tensor(), opacities, Tensor()};
  check_splats(s, bins, width, height, false);
  GSW_CHECK_ARG(weights.dim() == 3, "weights", "has shape ", shape_str(weights),
                " but expected [C, H, W]");
  const int64_t C = weights.size(0);
  check_tensor(weights, "weights", means2d, {C, height, width});
  const int64_t N = means2d.size(0);
  auto opts = means2d.options();
  Tensor V = torch::empty({N, C}, opts);
  Tensor hits = torch::empty({N}, opts.dtype(torch::kInt32));
  Tensor max_weight = torch::empty({N}, opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "gsw_contribution", [&] {
    RasterParams<scalar_t> p = raster_params<scalar_t>(s, bins, width, height, nullptr);
    ContributionParams<scalar_t> cp;
    cp.C = static_cast<int>(C);
    cp.weights = weights.data_ptr<scalar_t>();
    cp.contribution = V.data_ptr<scalar_t>();
    cp.hits = hits.data_ptr<int32_t>();
    cp.max_weight = max_weight.data_ptr<scalar_t>();
    if (means2d.is_cuda()) {
#ifdef GSW_WITH_CUDA
      const c10::cuda::CUDAGuard guard(means2d.device());
      cuda::contribution(p, cp);
#else
      no_cuda();
#endif
    } else {
      Tensor scratch = torch::empty({bins.gauss_ids.numel(), C + 2}, opts);
      cpu::contribution(p, cp, scratch.data_ptr<scalar_t>());
    }
  });
  return py::make_tuple(V, hits, max_weight);
}

}  // namespace

void register_ops(py::module_& m) {
  py::class_<Bins>(m, "TileBins",
                   "Tile binning of projected Gaussians: per tile, its Gaussians front to back.")
      .def(py::init(&bins_from_tensors), py::arg("tile_offsets"), py::arg("gauss_ids"), py::arg("entry_offsets"),
           py::arg("entry_slots"), py::arg("width"), py::arg("height"),
           "A binning from the tensors of an earlier one (no copy; shapes, dtypes and devices checked)")
      .def_readonly("tiles_x", &Bins::tiles_x)
      .def_readonly("tiles_y", &Bins::tiles_y)
      .def_readonly("tile_offsets", &Bins::tile_offsets, "[tiles_y * tiles_x + 1] int32")
      .def_readonly("gauss_ids", &Bins::gauss_ids, "[M] int32, per tile front to back")
      .def_readonly("entry_offsets", &Bins::entry_offsets, "[N + 1] int32")
      .def_readonly("entry_slots", &Bins::entry_slots, "[M] int32")
      .def_readonly("nonfinite", &Bins::nonfinite,
                    "bitmask of the inputs found non-finite by the projection (bit k: NONFINITE_FIELDS[k]); "
                    "0 when the projection ran without a nonfinite flag")
      .def_property_readonly("num_intersections", [](const Bins& b) { return b.gauss_ids.numel(); });

  m.def("project_forward", &project_forward, py::arg("means"), py::arg("quats"),
        py::arg("log_scales"), py::arg("opacity_logits"), py::arg("sh"), py::arg("sh_degree"),
        py::arg("viewmat"), py::arg("fx"), py::arg("fy"), py::arg("cx"), py::arg("cy"),
        py::arg("width"), py::arg("height"), py::arg("nonfinite") = py::none(),
        "Project Gaussians: -> (radii, means2d, conics, depths, colors, opacities). `nonfinite` (optional "
        "zeroed int32 [1]) receives the OR of the NONFINITE_FIELDS bits of inputs holding NaN/Inf");
  m.def("project_backward", &project_backward, py::arg("means"), py::arg("quats"),
        py::arg("log_scales"), py::arg("opacity_logits"), py::arg("sh"), py::arg("sh_degree"),
        py::arg("viewmat"), py::arg("fx"), py::arg("fy"), py::arg("cx"), py::arg("cy"),
        py::arg("width"), py::arg("height"), py::arg("radii"), py::arg("v_means2d"), py::arg("v_conics"),
        py::arg("v_depths"), py::arg("v_colors"), py::arg("v_opacities"),
        "VJP of project_forward: -> (v_means, v_quats, v_log_scales, v_opacity_logits, v_sh). Reads the inputs "
        "and radii only: conics, colours and opacities are recomputed");
  m.def("bin_gaussians", &bin_gaussians, py::arg("means2d"), py::arg("conics"), py::arg("opacities"),
        py::arg("radii"), py::arg("depths"), py::arg("width"), py::arg("height"),
        py::arg("nonfinite") = py::none(),
        "Sort projected Gaussians into 16x16 tiles (each one into the tiles of its opacity-aware ellipse "
        "within its radius rectangle); the projection's `nonfinite` flags are read back with the "
        "intersection count (TileBins.nonfinite)");
  py::tuple fields(kNumNonFiniteFields);
  for (int k = 0; k < kNumNonFiniteFields; ++k) fields[k] = kNonFiniteFields[k];
  m.attr("NONFINITE_FIELDS") = fields;
  m.def("rasterize_forward", &rasterize_forward, py::arg("means2d"), py::arg("conics"),
        py::arg("colors"), py::arg("opacities"), py::arg("depths"), py::arg("background"),
        py::arg("bins"), py::arg("width"), py::arg("height"),
        "Blend: -> (image [3,H,W], alpha [1,H,W], depth [1,H,W], final_T [H,W], n_contrib [H,W])");
  m.def("rasterize_backward", &rasterize_backward, py::arg("means2d"), py::arg("conics"),
        py::arg("colors"), py::arg("opacities"), py::arg("depths"), py::arg("background"),
        py::arg("bins"), py::arg("width"), py::arg("height"), py::arg("final_T"),
        py::arg("n_contrib"), py::arg("v_image"), py::arg("v_alpha") = py::none(),
        py::arg("v_depth") = py::none(),
        "VJP of rasterize_forward: -> (v_means2d, v_conics, v_colors, v_opacities, v_depths)");
  m.def("contribution", &contribution, py::arg("means2d"), py::arg("conics"),
        py::arg("opacities"), py::arg("bins"), py::arg("width"), py::arg("height"),
        py::arg("weights"),
        "Per-Gaussian weighted blending weights: -> (V [N,C], hits [N], max_weight [N])");
}

}  // namespace gsw::ops
