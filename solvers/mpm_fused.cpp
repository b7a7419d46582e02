// The fused MPM substep: G2P2G, one pass over the particles per substep (Wang et al. 2020,
// "A massively parallel and scalable multi-GPU material point method", claymore), on the CPU's
// bins and with the colour-free deterministic flush below.
//
//   primed?  no: sort, topology, split P2G (prime_grid)
//   grid update (p + dt f) / m + dt g, colliders          (split grid: MpmStepParams::split)
//   G2P2G over the bins: gather, update (v, C, F, x), particle collisions, material update,
//         split scatter of the updated particle into its old bin's dilated block
//   sort (re-bin by the new positions), topology (the next grid's leaves)
//   flush: each active leaf sums the dilated blocks reaching it in the old bins' order
//          (a particle outside its block: the split P2G of the sorted particles instead)
//
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
    update_grid(space);
    prime_grid(space);
  }
  MpmStepParams prm = step_params(dt);
  prm.split = true;
  const MpmGridView g = grid_view();
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
  fused_bin_leaf_.assign(bins_.leaf.begin(), bins_.leaf.begin() + std::ptrdiff_t(g.nbins));
  const bool far = std::any_of(fused_far_.begin(), fused_far_.end(), [](auto f) { return f; });
  sort_particles(space);
  update_grid(space);
  if (far) {  // a particle moved past the margin: scatter the re-sorted particles (same state)
    prime_grid(space);
    ++fused_fallbacks_;
  } else {
    flush_fused_blocks(space);
  }
  primed_ = true;
}

// Lists, per active leaf of the new grid, the parts of the dilated blocks that reach it, in the
// old bins' order (serial: a few dozen table look-ups per bin), then sums them (g2p2g_flush).
void MpmSolver::flush_fused_blocks(const exec::Space& space) {
  const std::vector<std::int32_t>& active = grid_.active_leaves();
  fused_slot_.assign(grid_.leaf_count(), -1);
  for (std::size_t li = 0; li < active.size(); ++li)
    fused_slot_[std::size_t(active[li])] = std::int32_t(li);
  const std::size_t nb = fused_bin_leaf_.size();
  fused_target_.assign(nb * 27, -1);
  fused_start_.assign(active.size() + 1, 0);
  const auto& nbr27 = grid_.nbr27();
  for (std::size_t b = 0; b < nb; ++b) {
    const Vec3i lc = fused_bin_leaf_[b];
    const std::int32_t own = grid_.find_leaf(lc * kLeafDim);
    for (int t = 0; t < 27; ++t) {
      const Vec3i d(t / 9 - 1, t / 3 % 3 - 1, t % 3 - 1);
      const std::int32_t leaf =
          own >= 0 ? nbr27[std::size_t(own)][std::size_t(t)] : grid_.find_leaf((lc + d) * kLeafDim);
      const std::int32_t slot = leaf >= 0 ? fused_slot_[std::size_t(leaf)] : -1;
      fused_target_[b * 27 + std::size_t(t)] = slot;
      if (slot >= 0) ++fused_start_[std::size_t(slot) + 1];
    }
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
  g2p2g_flush(space, grid_view(), settings_.order, p2g_blocks_.data(), fused_start_.data(),
              fused_items_.data());
}

}  // namespace amalgam
