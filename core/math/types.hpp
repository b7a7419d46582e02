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

constexpr const char* real_name() {
  return sizeof(Real) == 4 ? "float" : "double";
}

}  // namespace amalgam
