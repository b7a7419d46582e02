// Scalar and fixed-size Eigen types of the whole build. `Real` is float or double, chosen by the
// CMake option AMALGAM_REAL (float by default; the benchmarks state which they used).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <Eigen/LU>
#include <cstdint>

namespace amalgam {

#ifdef AMALGAM_REAL_DOUBLE
using Real = double;
#else
using Real = float;
#endif

using Vec3 = Eigen::Matrix<Real, 3, 1>;
using Mat3 = Eigen::Matrix<Real, 3, 3>;
using Vec3i = Eigen::Matrix<int, 3, 1>;
using Vec3d = Eigen::Matrix<double, 3, 1>;
using Mat3d = Eigen::Matrix<double, 3, 3>;

static_assert(sizeof(Vec3) == 3 * sizeof(Real), "Vec3 must be tightly packed for SoA views");
static_assert(sizeof(Mat3) == 9 * sizeof(Real), "Mat3 must be tightly packed for SoA views");

// Compensated state (issue 27, docs/validation.md). A particle's position and deformation
// gradient are each held as the unevaluated sum hi + lo of two Reals: hi is what every kernel
// reads, lo the part below hi's last bit. A substep's increment d is added exactly up to the
// rounding of lo (Knuth's TwoSum, TAOCP vol. 2 Sec. 4.2.2), so in the float build increments
// below one ulp of hi (a position's ulp is 6e-8 m at 1 m and 4e-6 m at 50 m; F's is 6e-8) add up
// instead of being rounded away, and a body at rest comes to rest where the double build does.
// Position and F both need it: with only one compensated, the other freezes while it moves on.
// Must not be compiled with reassociating flags (-ffast-math).
inline void add_compensated(Real& hi, Real& lo, Real d) {
  const Real b = lo + d;
  const Real s = hi + b;
  const Real bb = s - hi;
  lo = (hi - (s - bb)) + (b - bb);
  hi = s;
}
template <class M>  // Vec3, Mat3: element by element
inline void add_compensated(M& hi, M& lo, const M& d) {
  for (int e = 0; e < int(M::SizeAtCompileTime); ++e)
    add_compensated(hi.data()[e], lo.data()[e], d.data()[e]);
}

constexpr const char* real_name() {
  return sizeof(Real) == 4 ? "float" : "double";
}

}  // namespace amalgam
