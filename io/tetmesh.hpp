// Tetrahedral meshes in TetGen's format (`NAME.node` + `NAME.ele`, as Debian's `tetgen` binary
// writes them from a surface mesh: `tetgen -pq1.4a0.0001 mesh.off`). The peridynamics paper puts
// one particle at the barycentre of every tetrahedron (Sec. 5.2), with the tetrahedron's volume.
// Errors are InputErrors naming the file and line.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "core/geometry/tet_mesh.hpp"

namespace amalgam {

// Reads PATH.node and PATH.ele; `path` may name either file or their common stem. Node numbering
// may start at 0 or 1 (TetGen's -z); 10-node (second-order) tetrahedra keep their 4 corners;
// attributes and boundary markers are skipped. Checks indices, and that no tetrahedron is
// degenerate.
TetMesh load_tetgen(const std::string& path);

}  // namespace amalgam
