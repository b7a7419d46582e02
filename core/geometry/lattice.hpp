// Seeded jittered-lattice sampling shared by every object shape: lattice point (i, j, k) sits at
// lo + (i + 1/2, j + 1/2, k + 1/2) h plus a jitter of up to jitter * h / 2 per axis drawn from a
// splitmix64 hash of (seed, i, j, k), so the same scene gives the same particles on any machine
// and thread count. `inside(p)` keeps a point.
//
// A `LatticeSlice` samples only the planes i in [n0 * part / parts, n0 * (part + 1) / parts): the
// points come out in the same i-major order, so the slices of parts 0..parts-1 concatenated are
// the whole sample, point for point (a distributed set-up samples one slice per rank).
#pragma once

#include <cstdint>
#include <vector>

#include "core/math/types.hpp"

namespace amalgam {

namespace detail {
inline std::uint64_t splitmix64(std::uint64_t z) {
  z += 0x9e3779b97f4a7c15ULL;
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}
inline double centred_unit(std::uint64_t h) {
  return double(h >> 11) * (1.0 / 9007199254740992.0) - 0.5;
}
}  // namespace detail

// Part `part` of `parts`: items [begin(n), end(n)) of n (lattice planes, or a list such as a tet
// mesh's barycentres).
struct LatticeSlice {
  int part = 0, parts = 1;
  long long begin(long long n) const { return n * part / parts; }
  long long end(long long n) const { return n * (part + 1) / parts; }
  bool whole() const { return parts == 1; }
};

template <class Inside>
std::vector<Vec3> sample_lattice(const Vec3d& lo, const long long n[3], double h, double jitter,
                                 std::uint64_t seed, Inside&& inside,
                                 const LatticeSlice& slice = {}) {
  using detail::centred_unit;
  using detail::splitmix64;
  std::vector<Vec3> pts;
  for (long long i = slice.begin(n[0]); i < slice.end(n[0]); ++i)
    for (long long j = 0; j < n[1]; ++j)
      for (long long k = 0; k < n[2]; ++k) {
        const std::uint64_t id =
            splitmix64(seed ^ splitmix64(std::uint64_t(i) * 0x1000003ULL ^
                                         std::uint64_t(j) * 0x10007ULL ^ std::uint64_t(k)));
        Vec3d p = lo + h * Vec3d(double(i) + 0.5, double(j) + 0.5, double(k) + 0.5);
        p +=
            (jitter * h) * Vec3d(centred_unit(splitmix64(id + 1)), centred_unit(splitmix64(id + 2)),
                                 centred_unit(splitmix64(id + 3)));
        if (inside(p)) pts.push_back(p.cast<Real>());
      }
  return pts;
}

}  // namespace amalgam
