// Tetrahedral meshes: one peridynamic particle at the barycentre of every tetrahedron, with the
// tetrahedron's volume (peridynamics paper, Sec. 5.2).
#pragma once

#include <array>
#include <cstdint>
#include <vector>

#include "core/math/types.hpp"

namespace amalgam {

struct TetMesh {
  std::vector<Vec3d> nodes;
  std::vector<std::array<std::int32_t, 4>> tets;  // 0-based node indices
};

// Barycentres and (positive) volumes of the tetrahedra; mean edge length (the paper's lambda).
void tet_barycentres(const TetMesh& m, std::vector<Vec3>& x, std::vector<Real>& volume);
double tet_mean_edge(const TetMesh& m);

}  // namespace amalgam
