// Tetrahedral meshes in TetGen's format (`NAME.node` + `NAME.ele`, as Debian's `tetgen` binary
// writes them from a surface mesh: `tetgen -pq1.4a0.0001 mesh.off`). The peridynamics paper puts
// one particle at the barycentre of every tetrahedron (Sec. 5.2), with the tetrahedron's volume.
// Errors are InputErrors naming the file and line.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "core/math/types.hpp"

namespace amalgam {

struct TetMesh {
  std::vector<Vec3d> nodes;
  std::vector<std::array<std::int32_t, 4>> tets;  // 0-based node indices
};

// Reads PATH.node and PATH.ele; `path` may name either file or their common stem. Node numbering
// may start at 0 or 1 (TetGen's -z); 10-node (second-order) tetrahedra keep their 4 corners;
// attributes and boundary markers are skipped. Checks indices, and that no tetrahedron is
// degenerate.
TetMesh load_tetgen(const std::string& path);

// Barycentres and (positive) volumes of the tetrahedra; mean edge length (the paper's lambda).
void tet_barycentres(const TetMesh& m, std::vector<Vec3>& x, std::vector<Real>& volume);
double tet_mean_edge(const TetMesh& m);

}  // namespace amalgam
