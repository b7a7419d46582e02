// Sleeping blocks (issue 30 item 5; off by default, simulation.sleep). A block is a grid leaf's
// particle bin. Every particle keeps `rest_time`, how long it has moved slower than `speed` with
// a strain rate |sym C| below `strain_rate`. Each substep, after the sort:
//   decide      a bin sleeps when every particle in the bins within `halo` has rested for `time`
//               and no moving collider and no emitting emitter comes within `halo` of it; its
//               particles get v = C = 0 and are left out of P2G and G2P (MpmGridView::bin_end);
//               a bin that wakes resets its particles' rest_time
//   pin_nodes   after the grid update the sleeping bins' own leaves' nodes take v = 0: sleeping
//               material is a sticky static collider for the awake material resting on it
//   rest        after G2P the awake particles' rest_time grows by dt or returns to 0
// A sleeping particle does not move at all (x, v, F unchanged). Decisions are per bin from the
// particles' attributes only (serial neighbour lookups in bin order), so they are the same on every
// backend and thread count, and `rest_time` and `asleep` are particle attributes: checkpoints and
// frame retries carry them. On several MPI ranks (collective) every rank learns which bins of
// the others have rested, so the decisions are the single process's.
#pragma once

#include <cstdint>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/geometry/colliders.hpp"
#include "core/math/types.hpp"
#include "core/particles/particle_set.hpp"
#include "sparse_grid/binning.hpp"
#include "sparse_grid/sparse_grid.hpp"

namespace amalgam {

struct EmitterSpec;

struct SleepSettings {
  bool enabled = false;
  Real speed = Real(0.02);       // m/s
  Real strain_rate = Real(0.5);  // 1/s, of |sym C|
  Real time = Real(0.1);         // s at rest before a block sleeps
  Real halo = 0;                 // m; 0: two grid cells
};

class MpmSleep {
 public:
  MpmSleep(ParticleSet& ps, const SleepSettings& s);
  void decide(const exec::Space& space, ParticleSet& ps, const MpmAttributes& a,
              const BinTable& bins, Real dx, double time, const Collider* colliders, int ncolliders,
              const std::vector<EmitterSpec>& emitters, bool distributed = false);
  const std::uint32_t* bin_end() const { return bin_end_.data(); }
  void pin_nodes(const exec::Space& space, const SparseGrid& grid, const BinTable& bins,
                 Real* node4) const;
  void rest(const exec::Space& space, ParticleSet& ps, const MpmAttributes& a, Real dt) const;
  std::size_t sleeping(const ParticleSet& ps) const;  // particles asleep now
  ParticleSet::Id rest_time_attr() const { return rest_; }
  ParticleSet::Id asleep_attr() const { return asleep_; }

 private:
  SleepSettings s_;
  ParticleSet::Id rest_, asleep_;
  std::vector<std::uint32_t> bin_end_;
  std::vector<std::uint8_t> rested_, sleeps_;
};

}  // namespace amalgam
