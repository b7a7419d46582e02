// Shared test helpers for shape recovery (rest_shape_deviation of core/math/shape_matching.hpp).
#pragma once

#include <vector>

#include "core/math/shape_matching.hpp"
#include "solvers/mpm_solver.hpp"

namespace amalgam::test {

using amalgam::rest_shape_deviation;
inline std::vector<Vec3d> positions_by_id(const MpmSolver& s) {
  return s.positions_by_id();
}

}  // namespace amalgam::test
