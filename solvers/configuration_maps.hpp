// Per-object reference configurations of the adaptively updated Lagrangian MPM (A-ULMPM,
// Su et al. 2022, Secs. 5.1 and 5.7).
//
// Every object keeps its own configuration map: particles carry their reference positions X^s
// (attribute "X_s"), F^{sn} ("F_s") and F^{0s} ("F_0s"), and the object's index ("object").
// Weights and MLS matrices are measured at X^s, so the transfer kernels bin, scatter and gather
// at X^s (kernels/mpm_transfers.hpp, Lagrangian mode). An object's update policy is
//   eulerian          s = n: the configuration is reset every substep (EMPM, eq. 22)
//   total_lagrangian  s = 0: never reset (TLMPM, eq. 21)
//   adaptive          reset when the fraction of its particles with
//                     dJ_p = |det F_p^{sn} - 1| >= epsilon reaches eta (eq. 33)
// Objects live in disjoint lanes of the one reference grid: object k's X^s is its current
// position at the last reset plus k * lane along x, so objects never share a reference node
// and each keeps its own map (contact between objects then needs the global-grid coupling of
// Sec. 7.1, which this engine does not have yet: see docs/aulmpm.md).
// A reset (eq. 32 read at s := n): X^s = x, F^{0s} = F^{0n}, F^{sn} = I, and the stored velocity
// gradient is pushed to the new reference, grad_new v = grad_s v (F^{sn})^{-1}. The criterion is
// evaluated from F^{sn} at the start of each substep, so it needs no state of its own and a run
// resumed from a checkpoint takes the same decisions.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/math/types.hpp"
#include "core/particles/particle_set.hpp"

namespace amalgam {

enum class ConfigurationUpdate { Eulerian, TotalLagrangian, Adaptive };
const char* configuration_update_name(ConfigurationUpdate u);

struct ConfigurationPolicy {
  ConfigurationUpdate update = ConfigurationUpdate::Adaptive;
  Real epsilon = Real(0.5);  // dJ threshold per particle (paper: 0.5 for solids, 0.01 for fluids)
  Real eta = Real(0.1);      // fraction of marked particles that triggers a reset
};

// Counters of one object since the start of the run (not checkpointed: statistics only).
struct ConfigurationStats {
  std::uint64_t updates = 0;  // configuration resets
  std::uint64_t steps = 0;    // substeps the object took part in
  double update_seconds = 0;  // its share (by particle count) of reset + re-binning time
  double check_seconds = 0;   // its share of the criterion check (eq. 33), taken every substep
};

struct ConfigurationAttributes {
  ParticleSet::Id X_s = -1, F_s = -1, F_0s = -1, object = -1;
  static ConfigurationAttributes add_to(ParticleSet& ps);
};

class ConfigurationMaps {
 public:
  static constexpr int kMaxObjects = 32;
  // Reference-grid lane width along x per object, in grid cells.
  static constexpr int kLaneCells = 2048;

  // Registers an object; returns its index.
  int add_object(const ConfigurationPolicy& policy, std::size_t particles);
  int object_count() const { return int(policy_.size()); }
  const ConfigurationPolicy& policy(int k) const { return policy_[size_t(k)]; }
  const ConfigurationStats& stats(int k) const { return stats_[size_t(k)]; }
  Vec3 lane_offset(int k, Real dx) const { return Vec3(Real(k) * Real(kLaneCells) * dx, 0, 0); }

  // eq. 33 per object on the particles' F_s: fills `reset` (one flag per object) and returns
  // whether any object resets. Counts marked particles in a deterministic reduction; distributed
  // (collective): over every rank's particles, so every rank takes the same decisions.
  bool decide(const exec::Space& space, const ParticleSet& ps, const ConfigurationAttributes& a,
              std::vector<std::uint8_t>& reset, bool distributed = false);
  // Resets the configurations of the flagged objects (x, F and C are read from the MPM attributes).
  void reset(const exec::Space& space, ParticleSet& ps, const ConfigurationAttributes& a,
             ParticleSet::Id x, ParticleSet::Id F, ParticleSet::Id C, Real dx,
             const std::vector<std::uint8_t>& reset);
  // Books one substep: `check` seconds deciding (every object's share by particle count) and
  // `seconds` resetting and re-binning (the resetting objects' shares).
  void account(const std::vector<std::uint8_t>& reset, double check, double seconds);

 private:
  std::vector<ConfigurationPolicy> policy_;
  std::vector<ConfigurationStats> stats_;
  std::vector<std::size_t> count_;
};

}  // namespace amalgam
