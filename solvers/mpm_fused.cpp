// The fused MPM substep: G2P2G, one pass over the particles per substep (Wang et al. 2020,
// "A massively parallel and scalable multi-GPU material point method", claymore), on the CPU's
// bins and with the colour-free deterministic flush below.
//
//   primed?  no: sort, topology (dilated), split P2G (prime_grid)
//   grid update (p + dt f) / m + dt g, colliders          (split grid: MpmStepParams::split)
//   G2P2G over the bins: dilated gather, update (v, C, F, x), particle collisions, material
//         update, split scatter of the updated particle into its bin's dilated block
//   every particle inside its bin's dilated block: flush (each active leaf sums the blocks
//         reaching it in bin order); the bins, their order and the topology stay
//   else: sort (re-bin by the new positions), topology, split P2G of the re-sorted particles
//
// The particles are not re-sorted every substep: a bin keeps its particles while they stay
// within kG2P2GMargin nodes of its footprint, so the sort and the permutation run only every
// 11-40 substeps (docs/benchmarks.md, "How rarely the particles would need re-sorting").
// The scatter is dt-free because the next substep's dt (the CFL step) depends on the velocities
// this pass computes: the grid keeps the stress force in its own lanes and the grid update
// multiplies it by dt. The particle state is computed by the same per-particle functions as the
// two passes (g2p_particle, collide_particle, update_material_group, kirchhoff_lanes), so a
// fused substep moves the particles exactly as a two-pass substep on the same grid would; the
// grids differ in rounding (the force's dt applied at the node, blocks summed in another order).
#include <algorithm>

#include "kernels/material_update.hpp"
#include "solvers/mpm_solver.hpp"

namespace amalgam {

bool MpmSolver::fused_eligible() const {
  return fuses(settings_, ranks_ != nullptr);
}

void MpmSolver::prime_grid(const exec::Space& space) {
  MpmGridView g = grid_view();
  MpmStepParams prm = step_params(0);
  prm.split = true;
  grid_clear(space, g, prm);
  g.blocks = p2g_blocks_for(g.nbins, true);  // 8 lanes
  p2g(space, particle_view(), g, prm);
}

void MpmSolver::step_fused(const exec::Space& space, Real dt) {
  if (!primed_) {
    sort_particles(space);
    update_grid_fused(space);
    prime_grid(space);
  }
  MpmStepParams prm = step_params(dt);
  prm.split = true;
  const MpmGridView g = grid_view();  // with bin_nbr27 (update_grid_fused)
  grid_update(space, g, prm);
  const std::size_t reals = g.nbins * g2p2g_block_reals(settings_.order);
  const std::size_t budget =
      std::max(kG2P2GBlocksMinBudget, kG2P2GBlocksBytesPerParticle * particles_.size());
  if (reals * sizeof(Real) > budget) {  // the dilated blocks would not fit: two passes
    g2p(space, particle_view(), g, prm);
    collide_particles(space, dt);
    if (material_update_) update_materials(space, dt);
    primed_ = false;
    ++fused_unfused_;
    return;
  }
  if (p2g_blocks_.size() < reals) p2g_blocks_.resize(reals);
  fused_far_.assign(g.nbins, 0);
  const MaterialUpdateParams mu = material_params(dt);
  g2p2g(space, particle_view(), g, prm, material_update_ ? &mu : nullptr, p2g_blocks_.data(),
        fused_far_.data());
  // The particles stay in their bins, in their order, while every one's stencil lies inside its
  // bin's dilated block: the grid is then the blocks' sum over the same leaves. The first that
  // leaves it re-sorts them (every 11-40 substeps in the scenes measured, docs/benchmarks.md):
  // a function of the state, so every backend and thread count re-sorts at the same substeps.
  if (std::any_of(fused_far_.begin(), fused_far_.end(), [](auto f) { return f; })) {
    sort_particles(space);
    update_grid_fused(space);
    prime_grid(space);  // the split P2G of the re-sorted particles (the same state)
    ++fused_fallbacks_;
  } else {
    flush_fused_blocks(space);
  }
  primed_ = true;
}

// After a sort: the grid's leaves for the sorted bins and the leaves their dilated blocks reach
// (kG2P2GMargin nodes on the - side reach the -1 neighbours), each bin's 27 neighbour leaves for
// the dilated gather, and per active leaf the parts of the blocks that reach it, in bin order
// (serial: a few dozen table look-ups per bin), which every flush until the next sort uses.
void MpmSolver::update_grid_fused(const exec::Space& space) {
  fused_extra_.clear();
  for (const Vec3i& l : bins_.leaf)
    for (int t = 0; t < 27; ++t) {
      const Vec3i d(t / 9 - 1, t / 3 % 3 - 1, t % 3 - 1);
      if (d.minCoeff() < 0) fused_extra_.push_back(l + d);
    }
  grid_.update_topology(space, bins_, &fused_extra_);
  const std::size_t nb = bins_.count();
  fused_nbr27_.resize(nb);
  for (std::size_t b = 0; b < nb; ++b)
    fused_nbr27_[b] = grid_.nbr27()[std::size_t(grid_.nbr8()[b][0])];
  const std::vector<std::int32_t>& active = grid_.active_leaves();
  fused_slot_.assign(grid_.leaf_count(), -1);
  for (std::size_t li = 0; li < active.size(); ++li)
    fused_slot_[std::size_t(active[li])] = std::int32_t(li);
  fused_target_.assign(nb * 27, -1);
  fused_start_.assign(active.size() + 1, 0);
  for (std::size_t b = 0; b < nb; ++b)
    for (int t = 0; t < 27; ++t) {
      const std::int32_t leaf = fused_nbr27_[b][std::size_t(t)];
      const std::int32_t slot = leaf >= 0 ? fused_slot_[std::size_t(leaf)] : -1;
      fused_target_[b * 27 + std::size_t(t)] = slot;
      if (slot >= 0) ++fused_start_[std::size_t(slot) + 1];
    }
  for (std::size_t li = 0; li < active.size(); ++li) fused_start_[li + 1] += fused_start_[li];
  fused_items_.resize(fused_start_.back());
  std::vector<std::uint32_t>& at = fused_slot_cursor_;
  at.assign(fused_start_.begin(), fused_start_.end() - 1);
  for (std::size_t b = 0; b < nb; ++b)
    for (int t = 0; t < 27; ++t) {
      const std::int32_t slot = fused_target_[b * 27 + std::size_t(t)];
      if (slot >= 0)
        fused_items_[at[std::size_t(slot)]++] = std::uint32_t(b << 5) | std::uint32_t(t);
    }
}

// Each active leaf sums the dilated blocks reaching it in bin order (g2p2g_flush; the tables of
// update_grid_fused).
void MpmSolver::flush_fused_blocks(const exec::Space& space) {
  g2p2g_flush(space, grid_view(), settings_.order, p2g_blocks_.data(), fused_start_.data(),
              fused_items_.data());
}

}  // namespace amalgam
