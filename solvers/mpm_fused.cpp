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

#include "core/dist/comm.hpp"
#include "kernels/material_update.hpp"
#include "solvers/mpm_solver.hpp"

namespace amalgam {

bool MpmSolver::fused_eligible() const {
  return fuses(settings_, ranks_ != nullptr);
}

bool MpmSolver::sort_when_needed_eligible() const {
  return sorts_when_needed(settings_);
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
  const std::size_t budget = dilated_blocks_budget(particles_.size());
  if (reals * sizeof(Real) > budget) {  // the dilated blocks would not fit: two passes
    g2p(space, particle_view(), g, g2p_params(prm));
    after_g2p(space, dt);
    primed_ = false;
    ++fused_unfused_;
    return;
  }
  if (p2g_blocks_.size() < reals) p2g_blocks_.resize(reals);
  fused_far_.assign(g.nbins, 0);
  const MaterialUpdateParams mu = material_params(dt);
  prm.check = &folded_;  // the last particle pass of the substep
  prm.check_limits = check_limits();
  g2p2g(space, particle_view(), g, prm, material_update_ ? &mu : nullptr, p2g_blocks_.data(),
        fused_far_.data());
  fold_pending_ = true;
  // The particles stay in their bins, in their order, while every one's stencil lies inside its
  // bin's dilated block: the grid is then the blocks' sum over the same leaves. The first that
  // leaves it re-sorts them (every 11-40 substeps in the scenes measured, docs/benchmarks.md):
  // a function of the state, so every backend and thread count re-sorts at the same substeps.
  if (std::any_of(fused_far_.begin(), fused_far_.end(), [](auto f) { return f; })) {
    if (folded_.bad >= 0) {  // a particle blew up in this pass (its position may be NaN): not
      primed_ = false;       // binned; the next stable_dt reports it (the check of this pass)
      return;
    }
    sort_particles(space);
    update_grid_fused(space);
    prime_grid(space);  // the split P2G of the re-sorted particles (the same state)
    ++fused_fallbacks_;
  } else {
    flush_fused_blocks(space);
  }
  primed_ = true;
}

// The two passes re-sorted only when needed (simulation.sort "when_needed"): the fused path's bins,
// dilated blocks and flush tables with the two passes' own grid (no split: 4 lanes for MLS/APIC,
// PIC/FLIP's 8) and kernels.
//
//   primed and no far flag?  no: sort, topology (dilated), flush tables   (update_grid_fused)
//   P2G (p2g_dilated): each bin into its dilated block, each leaf sums its blocks in bin order
//       a particle outside its block (moved by the particle collisions)? sort, topology, P2G again
//   grid update (p / m, gravity, forces, colliders)
//   G2P (g2p_dilated): gather the dilated block, update the particles; far flag per bin
//   particle collisions, material update
//
// A function of the state alone (the particles' positions and the bins of the last sort), so
// every backend, thread count and vector path sorts at the same substeps; primed_ is reset where
// the fused path's is (a frame's start, restore, added or removed particles), so a resumed run
// sorts where the uninterrupted one did.
void MpmSolver::step_sorted_when_needed(const exec::Space& space, Real dt) {
  auto any = [](const std::vector<std::uint8_t>& f) {
    return std::any_of(f.begin(), f.end(), [](std::uint8_t x) { return x != 0; });
  };
  bool sorted = false;
  bool need = !primed_ || any(lazy_far_);
  // Several ranks sort together, where one process would (solvers/mpm_lazy_distributed.cpp).
  if (ranks_) need = lazy_sort_needed_distributed(space, need);
  if (need) {
    if (primed_) ++lazy_resorts_;
    sort_particles(space);
    sorted = true;
  }
  const int ch = p2g_channels(settings_.transfer, false);
  // The dilated blocks of the sorted bins within the budget? Otherwise the sorted particles take
  // the plain two passes this substep, and the next one sorts again. On several ranks the budget
  // of the whole run (every rank decides alike, as one process would).
  auto fits = [&] {
    std::uint64_t nb = bins_.count(), n = particles_.size();
    if (ranks_) {
      const std::vector<std::int64_t> all =
          dist::Comm::world().sum(std::vector<std::int64_t>{std::int64_t(nb), std::int64_t(n)});
      nb = std::uint64_t(all[0]), n = std::uint64_t(all[1]);
    }
    const std::size_t budget = dilated_blocks_budget(n);
    const std::size_t reals = nb * dilated_block_reals(settings_.order, ch);
    if (reals * sizeof(Real) > budget) return false;
    if (!ranks_ && p2g_blocks_.size() < reals) p2g_blocks_.resize(reals);
    return true;
  };
  auto plain_two_passes = [&] {
    update_grid(space);
    particle_to_grid(space, dt);
    update_grid_velocities(space, dt);
    if (folds_check())
      g2p(space, particle_view(), grid_view(), g2p_params(step_params(dt)));
    else
      grid_to_particle(space, dt);
    after_g2p(space, dt);
    lazy_far_.clear();
    primed_ = false;
    ++lazy_unfit_;
  };
  auto scatter = [&] {
    lazy_far_.assign(bins_.count(), 0);
    p2g_dilated(space, particle_view(), grid_view(), step_params(dt), p2g_blocks_.data(),
                fused_start_.data(), fused_items_.data(), fused_target_.data(), lazy_far_.data());
  };
  if (!fits()) {  // (kept bins always fit: they fitted when they were sorted)
    if (!sorted) sort_particles(space);
    return plain_two_passes();
  }
  if (ranks_) {
    if (sorted) update_grid_lazy_distributed(space);
    p2g_lazy_distributed(space, dt);
    g2p_lazy_distributed(space, dt);  // the grid update, the ghost rows, G2P with far flags
    collide_particles(space, dt);
    if (material_update_) update_materials(space, dt);
    primed_ = true;
    return;
  }
  if (sorted) update_grid_fused(space);
  scatter();
  if (any(lazy_far_)) {  // pushed past its block after the last G2P (particle collisions)
    ++lazy_resorts_;
    sort_particles(space);
    if (!fits()) return plain_two_passes();
    update_grid_fused(space);
    scatter();
  }
  update_grid_velocities(space, dt);
  g2p_dilated(space, particle_view(), grid_view(), g2p_params(step_params(dt)), lazy_far_.data());
  after_g2p(space, dt);  // (G2P ran the particle collisions and the check, unless this does)
  primed_ = true;
}

// After a sort: the grid's leaves for the sorted bins and the leaves their dilated blocks reach
// (kG2P2GMargin nodes on the - side reach the -1 neighbours), each bin's 27 neighbour leaves for
// the dilated gather, and per active leaf the parts of the blocks that reach it, in bin order
// (serial: a few dozen table look-ups per bin), which every flush until the next sort uses.
void MpmSolver::update_grid_fused(const exec::Space& space) {
  dilated_extra_leaves(fused_extra_);
  grid_.update_topology(space, bins_, &fused_extra_, topology_age());
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

// The leaves the dilated blocks reach beyond each bin's nbr8 (kG2P2GMargin nodes on the - side
// reach the -1 neighbours), which update_topology activates as extras.
void MpmSolver::dilated_extra_leaves(std::vector<Vec3i>& out) const {
  out.clear();
  for (const Vec3i& l : bins_.leaf)
    for (int t = 0; t < 27; ++t) {
      const Vec3i d(t / 9 - 1, t / 3 % 3 - 1, t % 3 - 1);
      if (d.minCoeff() < 0) out.push_back(l + d);
    }
}

std::uint32_t MpmSolver::topology_age() {
  const std::uint64_t age = steps_ > topology_step_ ? steps_ - topology_step_ : 1;
  topology_step_ = steps_;
  return std::uint32_t(std::min<std::uint64_t>(age, SparseGrid::kRetireAfter));
}

// Each active leaf sums the dilated blocks reaching it in bin order (g2p2g_flush; the tables of
// update_grid_fused).
void MpmSolver::flush_fused_blocks(const exec::Space& space) {
  g2p2g_flush(space, grid_view(), settings_.order, p2g_blocks_.data(), fused_start_.data(),
              fused_items_.data());
}

}  // namespace amalgam
