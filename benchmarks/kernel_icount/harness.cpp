// Serial driver of the CPU blend kernels (csrc/cpu/rasterize_cpu.cpp) without torch, for repeatable
// instruction counts (valgrind --tool=callgrind) and bitwise A/B of kernel changes: see run.sh.
//
// usage: harness DATADIR MODE REPEATS [OUT]
//   DATADIR: inputs written by dump_inputs.py; MODE: fwd | bwd (v_image = 1, black background, no
//   v_alpha / v_depth: the benchmark's image.sum().backward()) | bwdfull (background (0.25, 0.5, 1)
//   and pseudo-random v_image, v_alpha, v_depth); OUT: the outputs as raw float32 (compare with cmp).
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <string>
#include <vector>

#include "cpu/backend_cpu.h"

using namespace gsw;

template <class X>
static std::vector<X> read_raw(const std::string& path) {
  FILE* f = std::fopen(path.c_str(), "rb");
  if (!f) {
    std::perror(path.c_str());
    std::exit(1);
  }
  std::fseek(f, 0, SEEK_END);
  const long n = std::ftell(f);
  std::fseek(f, 0, SEEK_SET);
  std::vector<X> v(n / sizeof(X));
  if (std::fread(v.data(), 1, n, f) != size_t(n)) std::exit(1);
  std::fclose(f);
  return v;
}

static double thread_cpu_ms() {
  timespec t;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return t.tv_sec * 1e3 + t.tv_nsec * 1e-6;
}

int main(int argc, char** argv) {
  if (argc < 4) return 2;
  const std::string d = argv[1], mode = argv[2];
  const int reps = std::atoi(argv[3]);
  int N, W, H, tiles_x, tiles_y;
  long M;
  FILE* meta = std::fopen((d + "/meta.txt").c_str(), "r");
  if (!meta || std::fscanf(meta, "%d %d %d %d %d %ld", &N, &W, &H, &tiles_x, &tiles_y, &M) != 6) return 1;
  const auto means2d = read_raw<float>(d + "/means2d.bin"), conics = read_raw<float>(d + "/conics.bin"),
             colors = read_raw<float>(d + "/colors.bin"), opacities = read_raw<float>(d + "/opacities.bin"),
             depths = read_raw<float>(d + "/depths.bin"), final_T = read_raw<float>(d + "/final_T.bin");
  const auto tile_offsets = read_raw<int32_t>(d + "/tile_offsets.bin"), gauss_ids = read_raw<int32_t>(d + "/gauss_ids.bin"),
             entry_offsets = read_raw<int32_t>(d + "/entry_offsets.bin"),
             entry_slots = read_raw<int32_t>(d + "/entry_slots.bin"), n_contrib = read_raw<int32_t>(d + "/n_contrib.bin");
  const bool full = mode == "bwdfull";
  const float background[3] = {full ? 0.25f : 0.0f, full ? 0.5f : 0.0f, full ? 1.0f : 0.0f};
  RasterParams<float> p;
  p.N = N;
  p.width = W;
  p.height = H;
  p.bins = TileBins{tiles_x, tiles_y, M, tile_offsets.data(), gauss_ids.data(), entry_offsets.data(), entry_slots.data()};
  p.means2d = means2d.data();
  p.conics = conics.data();
  p.colors = colors.data();
  p.opacities = opacities.data();
  p.depths = depths.data();
  p.background = background;
  const long P = long(W) * H;
  std::vector<float> image(3 * P), alpha(P), depth(P), t_final(P), out;
  std::vector<int32_t> contrib(P);
  double best = 1e30;
  const auto timed = [&](auto&& call) {  // the fastest of reps calls, in thread CPU time
    for (int r = 0; r < reps; ++r) {
      const double c0 = thread_cpu_ms();
      call();
      best = std::min(best, thread_cpu_ms() - c0);
    }
  };
  if (mode == "fwd") {
    p.image = image.data();
    p.alpha = alpha.data();
    p.depth = depth.data();
    p.final_T = t_final.data();
    p.n_contrib = contrib.data();
    timed([&] { cpu::rasterize_forward(p); });
    for (const auto* v : {&image, &alpha, &depth, &t_final}) out.insert(out.end(), v->begin(), v->end());
    for (int32_t n : contrib) out.push_back(float(n));
  } else if (mode == "bwd" || full) {
    p.final_T = const_cast<float*>(final_T.data());
    p.n_contrib = const_cast<int32_t*>(n_contrib.data());
    std::vector<float> v_image(3 * P, 1.0f), v_alpha(P), v_depth(P);
    std::vector<float> v_means2d(2 * N), v_conics(3 * N), v_colors(3 * N), v_opacities(N), v_depths(N);
    RasterGradParams<float> g;
    if (full) {
      for (long i = 0; i < 3 * P; ++i) v_image[i] = float((i * 2654435761u) % 1000) / 500.0f - 1.0f;
      for (long i = 0; i < P; ++i) {
        v_alpha[i] = float((i * 40503u) % 997) / 997.0f - 0.5f;
        v_depth[i] = float((i * 69069u) % 991) / 9910.0f - 0.05f;
      }
      g.v_alpha = v_alpha.data();
      g.v_depth = v_depth.data();
    }
    g.v_image = v_image.data();
    g.v_means2d = v_means2d.data();
    g.v_conics = v_conics.data();
    g.v_colors = v_colors.data();
    g.v_opacities = v_opacities.data();
    g.v_depths = v_depths.data();
    timed([&] { cpu::rasterize_backward(p, g, -1); });  // no records budget: one pass
    for (const auto* v : {&v_means2d, &v_conics, &v_colors, &v_opacities, &v_depths})
      out.insert(out.end(), v->begin(), v->end());
  } else {
    return 2;
  }
  std::fprintf(stderr, "%s %s: min thread CPU %.1f ms per call\n", d.c_str(), mode.c_str(), best);
  if (argc > 4) {
    FILE* f = std::fopen(argv[4], "wb");
    std::fwrite(out.data(), sizeof(float), out.size(), f);
    std::fclose(f);
  }
  return 0;
}
