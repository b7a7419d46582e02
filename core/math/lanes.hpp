// One native vector register of T (float or double) as a GCC/Clang vector type, for kernels that
// run the same scalar algorithm on several particles at once (structure of arrays across lanes):
// 16 bytes (SSE2, the portable build), 32 with AVX, 64 with AVX-512F (the kernel variants of
// core/exec/simd.hpp are compiled with these flags). Operators are element-wise IEEE operations,
// so lane l computes exactly what the scalar code computes for particle l, whatever the other
// lanes hold; a comparison gives a mask (all ones or zero per lane) that selects with ?:.
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <cstdint>
#include <cstddef>
#include <cstring>
#include <type_traits>
#include <utility>

#if defined(__SSE2__)
#include <immintrin.h>
#endif

namespace amalgam::lanes {

#if defined(__AVX512F__)
inline constexpr int kBytes = 64;
#elif defined(__AVX__)
inline constexpr int kBytes = 32;
#else
inline constexpr int kBytes = 16;
#endif

template <class T>
struct Pack {
  typedef T type __attribute__((vector_size(kBytes)));
  static constexpr int kN = kBytes / int(sizeof(T));
};

template <class T>
using V = typename Pack<T>::type;
template <class T>
inline constexpr int kN = Pack<T>::kN;
template <class T>
using Mask = decltype(V<T>{} < V<T>{});

// All lanes set to s.
template <class T>
inline V<T> splat(T s) {
  return V<T>{} + s;
}

// (p[0], p[stride], p[2 stride], ...): one entry of kN consecutive structures, built in registers.
namespace detail {
template <class T, std::size_t... L>
inline V<T> gather_impl(const T* p, std::size_t stride, std::index_sequence<L...>) {
  return V<T>{p[L * stride]...};
}
}  // namespace detail
template <class T>
inline V<T> gather(const T* p, std::size_t stride) {
  return detail::gather_impl<T>(p, stride, std::make_index_sequence<kN<T>>{});
}

// The entries of n <= kN 3x3 matrices in storage order, one matrix per lane: m[e][l] =
// M[l].data()[e]; spare lanes hold the identity. store_mat3 writes lanes 0..n-1 back.
template <class T>
inline void load_mat3(const Eigen::Matrix<T, 3, 3>* M, int n, V<T>* m) {
  static_assert(sizeof(Eigen::Matrix<T, 3, 3>) == 9 * sizeof(T), "3x3 matrices stored densely");
  if (n == kN<T>) {
    for (int e = 0; e < 9; ++e) m[e] = gather(M[0].data() + e, 9);
    return;
  }
  for (int e = 0; e < 9; ++e) m[e] = splat(T(e % 4 == 0));
  for (int l = 0; l < n; ++l)
    for (int e = 0; e < 9; ++e) m[e][l] = M[l].data()[e];
}
template <class T>
inline void store_mat3(const V<T>* m, int n, Eigen::Matrix<T, 3, 3>* M) {
  for (int l = 0; l < n; ++l)
    for (int e = 0; e < 9; ++e) M[l].data()[e] = m[e][l];
}

// Helpers that let one algorithm be written once for a vector of lanes and for a single scalar
// (where a mask is a bool): whether any lane is set, a & ~b, per-lane std::sqrt.
namespace detail {
template <class M>
inline bool any_impl(const M& m) {
  std::uint64_t w[sizeof(M) / 8];
  std::memcpy(w, &m, sizeof w);
  std::uint64_t r = 0;
  for (std::uint64_t x : w) r |= x;
  return r != 0;
}
// Per-lane square root: the packed instruction where there is one (IEEE sqrt is correctly
// rounded, so it equals std::sqrt lane by lane; std::sqrt in a loop does not vectorise because
// of errno), else one lane at a time.
template <class T>
inline V<T> sqrt_impl(const V<T>& x) {
#if defined(__AVX512F__)
  if constexpr (sizeof(V<T>) == 64) {
    if constexpr (std::is_same_v<T, float>)
      return reinterpret_cast<V<T>>(_mm512_sqrt_ps(reinterpret_cast<__m512>(x)));
    else
      return reinterpret_cast<V<T>>(_mm512_sqrt_pd(reinterpret_cast<__m512d>(x)));
  }
#endif
#if defined(__AVX__)
  if constexpr (sizeof(V<T>) == 32) {
    if constexpr (std::is_same_v<T, float>)
      return reinterpret_cast<V<T>>(_mm256_sqrt_ps(reinterpret_cast<__m256>(x)));
    else
      return reinterpret_cast<V<T>>(_mm256_sqrt_pd(reinterpret_cast<__m256d>(x)));
  }
#endif
#if defined(__SSE2__)
  if constexpr (sizeof(V<T>) == 16) {
    if constexpr (std::is_same_v<T, float>)
      return reinterpret_cast<V<T>>(_mm_sqrt_ps(reinterpret_cast<__m128>(x)));
    else
      return reinterpret_cast<V<T>>(_mm_sqrt_pd(reinterpret_cast<__m128d>(x)));
  }
#endif
  V<T> r{};
  for (int l = 0; l < kN<T>; ++l) r[l] = std::sqrt(x[l]);
  return r;
}
}  // namespace detail

inline bool any(bool m) {
  return m;
}
inline bool any(const Mask<float>& m) {
  return detail::any_impl(m);
}
inline bool any(const Mask<double>& m) {
  return detail::any_impl(m);
}
inline bool andnot(bool a, bool b) {
  return a && !b;
}
inline Mask<float> andnot(const Mask<float>& a, const Mask<float>& b) {
  return a & ~b;
}
inline Mask<double> andnot(const Mask<double>& a, const Mask<double>& b) {
  return a & ~b;
}
inline float sqrt(float x) {
  return std::sqrt(x);
}
inline double sqrt(double x) {
  return std::sqrt(x);
}
inline V<float> sqrt(const V<float>& x) {
  return detail::sqrt_impl<float>(x);
}
inline V<double> sqrt(const V<double>& x) {
  return detail::sqrt_impl<double>(x);
}

}  // namespace amalgam::lanes
