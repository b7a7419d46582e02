// Internal to io/: OpenVDB files written the project's way (implemented in io/vdb_points.cpp).
#pragma once

#include <functional>
#include <string>

#include <openvdb/Grid.h>

#include "core/exec/exec.hpp"

namespace amalgam {

// Writes the grids `build` makes into a new temporary file beside `path`, under the space's thread
// limit (the grids are made and destroyed there too), replaces OpenVDB's random file UUID by one
// derived from the file's other bytes (identical content, identical file) and renames it into
// place. `compression`: io::Archive flags (io::COMPRESS_*), or -1 for OpenVDB's default. Throws
// InputError naming `path` and `what` on failure.
void write_vdb_file(const std::string& path, const exec::Space& space, const char* what,
                    const std::function<openvdb::GridCPtrVec()>& build, long compression = -1);

}  // namespace amalgam
