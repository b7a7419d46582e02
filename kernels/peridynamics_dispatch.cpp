// The public entry points of the peridynamic bond passes, compiled once per instruction set
// (kernels/peridynamics_passes.cpp; core/exec/simd.hpp): each call runs the variant of
// exec::simd_path(). (Apart from kernels/simd_dispatch.cpp, the MPM kernels' entry points: one
// method family per kernel file, scripts/check_layers.sh.)
#include "core/exec/simd.hpp"
#include "kernels/peridynamics.hpp"

namespace amalgam {

AMALGAM_SIMD_DECLARE(PdKernelTable, pd_kernels)

// The peridynamic bond passes: the block loops over a row's bonds at the path's width, the sums
// in the same logical lanes (PdBonds::lane) on every path.
void pd_dilatation(const exec::Space& space, const PdView& p, PdBonds& bonds, const PdParams& prm,
                   PdScratch* scratch) {
  AMALGAM_SIMD_PICK(pd_kernels).dilatation(space, p, bonds, prm, scratch);
}
void pd_forces(const exec::Space& space, const PdView& p, PdBonds& bonds, const PdParams& prm,
               bool fracture, Vec3* force, Mat3* stress, PdScratch* scratch,
               std::uint64_t* intact) {
  AMALGAM_SIMD_PICK(pd_kernels)
      .forces(space, p, bonds, prm, fracture, force, stress, scratch, intact);
}
std::uint64_t pd_damage(const exec::Space& space, const PdView& p, const PdBonds& bonds) {
  return AMALGAM_SIMD_PICK(pd_kernels).damage(space, p, bonds);
}

}  // namespace amalgam
