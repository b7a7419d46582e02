// A-ULMPM and TL-MPM (Su et al. 2022), a component of MpmSolver (solvers/mpm_solver.hpp): every
// object keeps its own reference configuration s (solvers/configuration_maps.hpp) in which the
// kernels' Lagrangian mode measures weights, stress and strain. In the substep it:
//   update_configurations   replaces sorting: eq. 33 per object, resets of the objects that need
//                           one, and re-binning at X^s only when a reference changed (the weights
//                           stay valid otherwise: what makes TL/A-UL cheaper than Eulerian MPM)
//   couple_objects          after the grid update: contact between objects through a global grid
//                           at the nodes' positions q_i^{n+1} (eq. 27; solvers/object_contact)
//   keep_split              after the return mapping: F_s = F (F^{0s})^-1, so F = F_s F_0s (eq. 32)
// Explicit only.
#pragma once

#include <cstdint>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/particles/particle_set.hpp"
#include "kernels/mpm_transfers.hpp"
#include "solvers/configuration_maps.hpp"
#include "solvers/object_contact.hpp"

namespace amalgam {

class MpmSolver;

class MpmAul {
 public:
  MpmAul(ParticleSet& particles, const ObjectContactSettings& contact);

  // The particles [first, first + n) form one object (of `total` particles over every rank: a
  // distributed set-up's slice) with the given update policy: references X^s = x in the object's
  // lane of the reference grid, F_s = F_0s = I.
  void add_object(ParticleSet& particles, const Vec3* x, std::size_t first, std::size_t n,
                  std::size_t total, const ConfigurationPolicy& policy, Real dx);
  void update_configurations(const exec::Space& space, MpmSolver& mpm);
  void couple_objects(const exec::Space& space, MpmSolver& mpm, Real dt);
  void keep_split(const exec::Space& space, ParticleSet& particles, ParticleSet::Id F);
  // The particle view's reference fields (X_ref, F_s, F_0s).
  void fill_view(MpmParticleView& v, ParticleSet& particles) const;
  // Particles may have been replaced (retry, checkpoint): re-bin before the next transfer.
  void invalidate_bins() { bins_valid_ = false; }

  // Whether couple_objects acts (contact mode not none, two objects or more).
  bool contact_active() const;
  const ConfigurationAttributes& attributes() const { return cattr_; }
  const ConfigurationMaps& maps() const { return maps_; }
  // Reference nodes whose velocity the contact changed since the start of the run, the wall time
  // in couple_objects, and the contact points of the last substep.
  std::uint64_t contact_nodes() const { return contact_nodes_; }
  double contact_seconds() const { return contact_seconds_; }
  std::size_t contact_point_count() const { return contact_.point_count(); }

 private:
  ObjectContactSettings contact_settings_;
  ConfigurationAttributes cattr_;
  ConfigurationMaps maps_;
  std::vector<std::uint8_t> reset_flags_;
  bool bins_valid_ = false;  // bins and topology match X^s
  ObjectContact contact_;
  std::uint64_t contact_nodes_ = 0;
  double contact_seconds_ = 0;
};

}  // namespace amalgam
