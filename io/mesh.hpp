// Triangle mesh files for solids and colliders: OBJ, OFF, PLY (ASCII or binary little-endian) and
// STL (ASCII or binary) readers. Errors are InputErrors naming the file and line. The geometry (checks, sampling,
// distance fields) is in core/geometry/triangle_mesh.hpp.
#pragma once

#include <string>

#include "core/geometry/triangle_mesh.hpp"

namespace amalgam {

// Reads .obj, .off, .ply or .stl by extension (a regular file).
TriangleMesh load_mesh(const std::string& path);
// The same from the file's bytes (`name` gives the extension and the name in messages).
TriangleMesh parse_mesh(const std::string& bytes, const std::string& name);

}  // namespace amalgam
