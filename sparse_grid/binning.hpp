// Stable binning of particles by grid leaf (8^3 nodes), rebuilt every substep.
//
// key(p) = leaf coordinate of the particle's stencil base node, base >> 3, linearised over the
// bounding box of occupied leaves into 32 bits. Particles are stably LSD-radix-sorted by key
// (11-bit digits, a fixed chunk count, so the permutation never depends on the thread count),
// then every attribute of the ParticleSet is permuted. Bins are the runs of equal key.
#pragma once

#include <cstdint>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/math/types.hpp"
#include "core/particles/particle_set.hpp"

namespace amalgam {

struct BinTable {
  std::vector<std::uint32_t> start;  // nbins + 1 offsets into the sorted particle array
  std::vector<Vec3i> leaf;           // leaf coordinate (node index >> 3) of each bin
  std::size_t count() const { return leaf.size(); }
};

class ParticleBinning {
 public:
  // The permutation: one 32-bit word per particle. The keys, the sort's second buffers and the
  // bins' run flags live in the particle set's spare (ParticleSet::spare_words, counted in its
  // bytes_per_particle), free until the permute that ends the sort.
  static constexpr std::size_t kScratchBytesPerParticle = sizeof(std::uint32_t);
  // `order` is the B-spline order (1, 2 or 3) whose stencil base defines the key.
  // Sorts `ps` in place by leaf key (attribute `x_id` holds positions), fills `bins`.
  // With `id_id` (an int32 attribute of unique particle ids), the particles of a bin are ordered
  // by id: the order is then (leaf, id), a function of the particles alone, whatever order they
  // came in (a distributed run's ranks hold and migrate the particles of their leaves, and a
  // node's P2G sum must add them in the single process's order; docs/architecture.md). Without
  // it the sort is stable: a bin keeps the particles' previous relative order.
  // Throws SimulationError naming the first particle whose position is not finite.
  void sort_and_bin(const exec::Space& space, ParticleSet& ps, ParticleSet::Id x_id, Real dx,
                    int order, BinTable& bins, ParticleSet::Id id_id = -1);

 private:
  std::vector<std::uint32_t> perm_;
  std::vector<std::uint32_t> hist_;
};

}  // namespace amalgam
