// The public entry points of the kernel files compiled once per instruction set
// (core/exec/simd.hpp; kernels/CMakeLists.txt, amalgam_simd_variants): each call runs the
// variant of exec::simd_path().
#include <stdexcept>

#include "core/exec/simd.hpp"
#include "kernels/material_update.hpp"
#include "kernels/mpm_transfers.hpp"
#include "kernels/peak_flops.hpp"

namespace amalgam {

AMALGAM_SIMD_DECLARE(MpmKernelTable, mpm_kernels)
AMALGAM_SIMD_DECLARE(MaterialKernelTable, material_kernels)
AMALGAM_SIMD_DECLARE(PeakFlopsTable, peak_flops_kernels)

namespace {
const MpmKernelTable& mpm() {
  return AMALGAM_SIMD_PICK(mpm_kernels);
}
// The node loops that clear and apply colliders run the baseline's code on every path: measured
// alternated by CPU time, the compiler's AVX2 and AVX-512 builds of the node loops were 11 % and
// 4 % slower than the baseline's (docs/benchmarks.md, "Run-time vector width"). The grid update
// takes the path's code: its collider-free leaves are explicit vectors of whole nodes
// (update_free_leaf, kernels/mpm_transfers.cpp), the same bits on every path.
const MpmKernelTable& mpm_nodes() {
  return isa_baseline::mpm_kernels;
}
}  // namespace

void grid_clear(const exec::Space& space, const MpmGridView& g, const MpmStepParams& prm) {
  mpm_nodes().grid_clear(space, g, prm);
}
void p2g(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
         const MpmStepParams& prm) {
  mpm().p2g(space, p, g, prm);
}
void clear_node4(const exec::Space& space, const MpmGridView& g, Real* out) {
  mpm_nodes().clear_node4(space, g, out);
}
void p2g_positions(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                   const MpmStepParams& prm, Real* out) {
  mpm().p2g_positions(space, p, g, prm, out);
}
void grid_update(const exec::Space& space, const MpmGridView& g, const MpmStepParams& prm) {
  mpm().grid_update(space, g, prm);
}
void grid_apply_colliders(const exec::Space& space, const MpmGridView& g,
                          const MpmStepParams& prm) {
  mpm_nodes().grid_apply_colliders(space, g, prm);
}
void g2p(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
         const MpmStepParams& prm) {
  mpm().g2p(space, p, g, prm);
}
void p2g_blocks(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                const MpmStepParams& prm, const std::uint32_t* bins, std::size_t nbins, Real* keep,
                const std::function<void(std::size_t, const Real*, int)>& take) {
  mpm().p2g_blocks(space, p, g, prm, bins, nbins, keep, take);
}

void g2p2g(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
           const MpmStepParams& prm, const MaterialUpdateParams* mu, Real* blocks,
           std::uint8_t* far) {
  if (g.nbins > 0 && !g.bin_nbr27)  // the dilated gather's leaves (MpmSolver::update_grid_fused)
    throw std::logic_error("g2p2g: the grid view has no bin_nbr27");
  mpm().g2p2g(space, p, g, prm, mu, blocks, far);
}
void g2p2g_flush(const exec::Space& space, const MpmGridView& g, int order, const Real* blocks,
                 const std::uint32_t* start, const std::uint32_t* items) {
  mpm().g2p2g_flush(space, g, order, blocks, start, items);
}
void p2g_dilated(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                 const MpmStepParams& prm, Real* blocks, const std::uint32_t* start,
                 const std::uint32_t* items, const std::int32_t* target, std::uint8_t* far) {
  mpm().p2g_dilated(space, p, g, prm, blocks, start, items, target, far);
}
void g2p_dilated(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                 const MpmStepParams& prm, std::uint8_t* far) {
  if (g.nbins > 0 && !g.bin_nbr27)  // the dilated gather's leaves (MpmSolver::update_grid_fused)
    throw std::logic_error("g2p_dilated: the grid view has no bin_nbr27");
  mpm().g2p_dilated(space, p, g, prm, far);
}
void sum_dilated_leaves(const exec::Space& space, const MpmGridView& g, int order, int ch,
                        const Real* blocks, const std::uint32_t* start,
                        const std::uint32_t* items) {
  mpm().sum_dilated_leaves(space, g, order, ch, blocks, start, items);
}
// The material update's SVDs run a vector of particles at a time: the path's width. The particle
// collisions run the baseline's code: only their half-space test is a loop across particles.
void update_material_state(const exec::Space& space, const MpmParticleView& p,
                           const MaterialUpdateParams& prm) {
  AMALGAM_SIMD_PICK(material_kernels).update_material_state(space, p, prm);
}
void collide_particles(const exec::Space& space, const MpmParticleView& p,
                       const Collider* colliders, int n, Real time) {
  isa_baseline::material_kernels.collide_particles(space, p, colliders, n, time);
}
// The diagnostics' energies take their SVDs at the path's width (bitwise the same on every path).
void energy_densities(const MpmParticleView& p, const MaterialParams* mats, std::size_t q0,
                      std::size_t q1, Real* e) {
  AMALGAM_SIMD_PICK(material_kernels).energy_densities(p, mats, q0, q1, e);
}
double peak_flops_run(const exec::Space& space, int chunks, int iters, Real* sink) {
  return AMALGAM_SIMD_PICK(peak_flops_kernels).run(space, chunks, iters, sink);
}

}  // namespace amalgam
