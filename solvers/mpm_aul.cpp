#include "solvers/mpm_aul.hpp"

#include <chrono>

#include "solvers/mpm_solver.hpp"

namespace amalgam {

MpmAul::MpmAul(ParticleSet& particles, const ObjectContactSettings& contact)
    : contact_settings_(contact), cattr_(ConfigurationAttributes::add_to(particles)) {}

void MpmAul::add_object(ParticleSet& particles, const Vec3* x, std::size_t first, std::size_t n,
                        std::size_t total, const ConfigurationPolicy& policy, Real dx) {
  const int k = maps_.add_object(policy, total);
  const Vec3 offset = maps_.lane_offset(k, dx);
  Vec3* Xs = particles.vec3(cattr_.X_s);
  Mat3* Fs = particles.mat3(cattr_.F_s);
  Mat3* F0s = particles.mat3(cattr_.F_0s);
  std::int32_t* obj = particles.int32(cattr_.object);
  for (std::size_t p = first; p < first + n; ++p) {
    Xs[p] = x[p] + offset;
    Fs[p] = F0s[p] = Mat3::Identity();
    obj[p] = k;
  }
  bins_valid_ = false;
}

void MpmAul::fill_view(MpmParticleView& v, ParticleSet& particles) const {
  v.X_ref = particles.vec3(cattr_.X_s);
  v.F_s = particles.mat3(cattr_.F_s);
  v.F_0s = particles.mat3(cattr_.F_0s);
}

bool MpmAul::contact_active() const {
  return contact_settings_.mode != ObjectContactMode::None && maps_.object_count() > 1;
}

void MpmAul::update_configurations(const exec::Space& space, MpmSolver& mpm) {
  const auto t0 = std::chrono::steady_clock::now();
  ParticleSet& ps = mpm.particles_;
  const bool any = maps_.decide(space, ps, cattr_, reset_flags_, mpm.distributed());
  const auto t1 = std::chrono::steady_clock::now();
  if (any)
    maps_.reset(space, ps, cattr_, mpm.attr_.x, mpm.attr_.F, mpm.attr_.C, mpm.settings_.dx,
                reset_flags_);
  if (any || !bins_valid_) {
    mpm.sort_particles(space);
    mpm.update_grid(space);
    // Which object owns each reference leaf (for the contact), and the check that no two
    // objects share reference nodes (an object that left its lane), with or without contact.
    // Distributed: over the leaves this rank owns (solvers/mpm_distributed.cpp).
    if (maps_.object_count() > 1) {
      ContactRanks ranks;
      if (mpm.distributed()) {
        ranks.owned = &mpm.owned_leaf_list();
        ranks.owner = [&mpm](const Vec3i& l) { return mpm.leaf_owner(l); };
        ranks.peers = &mpm.exchange_peers();
      }
      contact_.map_leaves(space, mpm.grid_, mpm.bins_, ps.int32(cattr_.object),
                          mpm.distributed() ? &ranks : nullptr);
    }
    bins_valid_ = true;
  }
  using seconds = std::chrono::duration<double>;
  maps_.account(reset_flags_, seconds(t1 - t0).count(),
                seconds(std::chrono::steady_clock::now() - t1).count());
}

void MpmAul::couple_objects(const exec::Space& space, MpmSolver& mpm, Real dt) {
  if (!contact_active()) return;
  const auto t0 = std::chrono::steady_clock::now();
  contact_nodes_ += contact_.apply(space, mpm.grid_view(), mpm.grid_.node4(mpm.channels_.positions),
                                   contact_settings_, mpm.settings_.dx, dt);
  if (mpm.distributed()) mpm.exchange_ghost_rows(space);  // G2P reads the corrected ghosts
  contact_seconds_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

void MpmAul::keep_split(const exec::Space& space, ParticleSet& particles, ParticleSet::Id F_id) {
  // The return mapping changed F^{0n}: keep F = F_s F_0s (eq. 32) with F_s = F (F^{0s})^{-1}.
  const Mat3* F = particles.mat3(F_id);
  Mat3* Fs = particles.mat3(cattr_.F_s);
  const Mat3* F0s = particles.mat3(cattr_.F_0s);
  exec::parallel_for(space, "aul.sync_F_s", exec::Index(particles.size()),
                     [=](exec::Index i) { Fs[i] = F[i] * F0s[i].inverse(); });
}

}  // namespace amalgam
