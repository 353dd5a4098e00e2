// Lane blocks of the CPU blending kernels: kLanes pixels of a tile row as one GCC vector
// (8 x float = one AVX2 register in the x86-64-v3 clone; 8 x double for the float64 build).
// The per-pixel functions of core/math.h run on these vectors unchanged (ScalarOf below): one
// implementation of the math, compiled lane-parallel, with explicit selects instead of the
// compiler's if-conversion of scalar loops.
#pragma once

#include <cstdint>

#include "core/math.h"
#include "cpu/parallel.h"

namespace gsw::cpu {

constexpr int kLanes = 8;

template <typename T>
struct Lanes;
template <>
struct Lanes<float> {
  typedef float V __attribute__((vector_size(kLanes * sizeof(float))));
  typedef int32_t M __attribute__((vector_size(kLanes * sizeof(int32_t))));  // comparison masks
};
template <>
struct Lanes<double> {
  typedef double V __attribute__((vector_size(kLanes * sizeof(double))));
  typedef int64_t M __attribute__((vector_size(kLanes * sizeof(int64_t))));
};
template <typename T>
using VecT = typename Lanes<T>::V;
template <typename T>
using MaskT = typename Lanes<T>::M;
typedef int32_t VecI32 __attribute__((vector_size(kLanes * sizeof(int32_t))));

template <typename T>
GSW_CPU_INLINE VecT<T> splat(T x) {
  return VecT<T>{} + x;
}
template <typename T>
GSW_CPU_INLINE VecT<T> iota() {
  VecT<T> v;
  for (int q = 0; q < kLanes; ++q) v[q] = T(q);
  return v;
}
template <typename V>
GSW_CPU_INLINE V load(const void* p) {
  V v;
  __builtin_memcpy(&v, p, sizeof(V));
  return v;
}
template <typename V>
GSW_CPU_INLINE void store(void* p, V v) {
  __builtin_memcpy(p, &v, sizeof(V));
}
// Sum of a vector's lanes, in a fixed tree order ((q, q + 4), then (q, q + 2), then (q, q + 1)).
template <typename V>
GSW_CPU_INLINE auto lane_sum(V v) {
  v += __builtin_shufflevector(v, v, 4, 5, 6, 7, 0, 1, 2, 3);
  v += __builtin_shufflevector(v, v, 2, 3, 0, 1, 6, 7, 4, 5);
  v += __builtin_shufflevector(v, v, 1, 0, 3, 2, 5, 4, 7, 6);
  return v[0];
}
// Bit q set where lane q of an int32 mask is set.
GSW_CPU_INLINE uint32_t lane_bits(VecI32 m) {
#if defined(__SSE__)
  typedef float F4 __attribute__((vector_size(16)));
  const auto lo = __builtin_shufflevector(m, m, 0, 1, 2, 3), hi = __builtin_shufflevector(m, m, 4, 5, 6, 7);
  return uint32_t(__builtin_ia32_movmskps(reinterpret_cast<F4>(lo))) |
         uint32_t(__builtin_ia32_movmskps(reinterpret_cast<F4>(hi))) << 4;
#else
  uint32_t b = 0;
  for (int q = 0; q < kLanes; ++q) b |= uint32_t(m[q] != 0) << q;
  return b;
#endif
}
// The int32 lane mask of bits (lane q set where bit q is).
GSW_CPU_INLINE VecI32 bits_mask(uint32_t bits) {
  const VecI32 bit = {1, 2, 4, 8, 16, 32, 64, 128};
  return ((VecI32{} + int32_t(bits)) & bit) == bit;
}
static_assert(kLanes == 8, "lane_bits / bits_mask assume 8 lanes");
// An int32 lane mask as the comparison mask of T lanes.
template <typename T>
GSW_CPU_INLINE MaskT<T> mask_as(VecI32 m) {
  return __builtin_convertvector(m, MaskT<T>);
}
// A mask as int32 lanes (-1 where set).
GSW_CPU_INLINE VecI32 mask_i32(Lanes<float>::M m) { return m; }
GSW_CPU_INLINE VecI32 mask_i32(Lanes<double>::M m) { return __builtin_convertvector(m, VecI32); }

}  // namespace gsw::cpu

namespace gsw {

template <>
struct ScalarOf<cpu::VecT<float>> {
  using type = float;
};
template <>
struct ScalarOf<cpu::VecT<double>> {
  using type = double;
};

template <>
struct FloatBits<cpu::VecT<float>> {
  using V = cpu::VecT<float>;
  using I = cpu::Lanes<float>::M;
  static GSW_CPU_INLINE I to_bits(V f) { return reinterpret_cast<I>(f); }
  static GSW_CPU_INLINE V from_bits(I i) { return reinterpret_cast<V>(i); }
};
template <>
struct HostBlendExp<cpu::VecT<float>> {
  static GSW_CPU_INLINE cpu::VecT<float> apply(cpu::VecT<float> x) { return host_blend_exp_f32(x); }
};
template <>
struct HostBlendExp<cpu::VecT<double>> {
  using V = cpu::VecT<double>;
  static GSW_CPU_INLINE V apply(V x) {
    for (int q = 0; q < cpu::kLanes; ++q) x[q] = host_blend_exp(x[q]);
    return x;
  }
};

}  // namespace gsw
