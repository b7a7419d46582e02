// Contact between A-ULMPM objects through a global grid (kernels/object_contact.hpp): owns the
// contact points (one per reference node with mass), their binning and the global SparseGrid.
// Per substep, after the grid velocities are final and before G2P:
//   collect (reference nodes -> points at q^{n+1}) -> bin -> activate global leaves ->
//   scatter -> gather and correct the reference velocities.
#pragma once

#include <cstdint>
#include <functional>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/particles/particle_set.hpp"
#include "kernels/object_contact.hpp"
#include "sparse_grid/binning.hpp"
#include "sparse_grid/sparse_grid.hpp"

namespace amalgam {

struct ObjectContactSettings {
  ObjectContactMode mode = ObjectContactMode::Stick;
  Real friction = 0;  // Coulomb coefficient between objects (separate)
};

// Distributed runs (solvers/mpm_distributed.cpp): the active reference leaves this rank owns and
// the owner of any leaf. Each rank collects the contact points of its own leaves; every rank then
// holds all of them in the single process's order (reference leaf, node) and scatters them onto
// its own copy of the global grid, and corrects the nodes of its own leaves: bitwise the single
// process on every rank count.
struct ContactRanks {
  const std::vector<std::int32_t>* owned = nullptr;
  std::function<int(const Vec3i&)> owner;
  const std::vector<int>* peers = nullptr;  // the owners of every leaf a bin reaches, and more
};

class ObjectContact {
 public:
  ObjectContact();

  // After the reference grid's topology changed: which object owns each reference leaf (from
  // the particles of the bins that reach it). Throws SimulationError when two objects reach the
  // same reference leaf (an object left its lane: ConfigurationMaps::kLaneCells).
  // Distributed (`ranks` set; collective): the owners learn the objects of their leaves that
  // other ranks' bins reach; apply then works on the owned leaves.
  void map_leaves(const exec::Space& space, const SparseGrid& ref, const BinTable& bins,
                  const std::int32_t* particle_object, const ContactRanks* ranks = nullptr);
  // Couples the reference-grid velocities (ref.a = (m, v) after the grid update or the implicit
  // solve; ref.b = v_new - v_old for PIC/FLIP, else null) of different objects. `q` holds the
  // reference nodes' (m, m q^n). Returns the number of reference nodes whose velocity changed
  // (distributed: on all ranks; collective).
  std::size_t apply(const exec::Space& space, const MpmGridView& ref, const Real* q,
                    const ObjectContactSettings& settings, Real dx, Real dt);

  const SparseGrid& global_grid() const { return grid_; }
  std::size_t point_count() const { return points_.size(); }

 private:
  ContactPointView point_view();
  void reduce_boxes(ContactBoxes& boxes) const;         // distributed: every rank's boxes
  std::uint32_t gather_points(const MpmGridView& ref);  // distributed: every rank's points
  bool distributed_ = false;
  std::size_t mapped_active_ = 0;  // the reference grid's active leaves at map_leaves
  std::vector<std::int32_t> leaf_object_;
  int objects_ = 0;  // 1 + the largest object index on the reference grid
  // The reference grid's active leaves by coordinate: the points' order (hence the global
  // scatter's summation order) must not depend on the leaf table's history, or a run resumed
  // from a checkpoint (fresh leaf table) would differ in the last bits.
  std::vector<std::int32_t> ordered_leaves_;
  std::vector<std::uint32_t> count_, start_;
  ParticleSet points_;
  ParticleSet::Id x_ = -1, v_ = -1, m_ = -1, object_ = -1, leaf_ = -1, offset_ = -1;
  ParticleBinning binning_;
  BinTable bins_;
  SparseGrid grid_;
};

}  // namespace amalgam
