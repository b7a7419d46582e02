// Triangle mesh files for solids and colliders: OBJ, OFF and PLY (ASCII or binary little-endian)
// readers. Errors are InputErrors naming the file and line. The geometry (checks, sampling,
// distance fields) is in core/geometry/triangle_mesh.hpp.
#pragma once

#include <string>

#include "core/geometry/triangle_mesh.hpp"

namespace amalgam {

// Reads .obj, .off or .ply by extension.
TriangleMesh load_mesh(const std::string& path);

}  // namespace amalgam
