// Structure-of-arrays particle storage with named attributes.
//
// Each attribute is one contiguous array of `width` scalars per particle (Real or int32), so a
// kernel receives plain pointers (`vec3("x")` is a Vec3*, `mat3("F")` a Mat3*). `permute` gathers
// through ONE spare of spare_words_per_particle() 32-bit words (a Vec3's width): an attribute of
// that width is gathered into the spare and the two are swapped; a narrower one (scalars) is
// gathered into it and copied back, a wider one (Mat3) a spare's width at a time, each group
// copied back in the pass that gathers the next. ParticleBinning's sort keeps its keys, second
// buffers and run flags in the same spare (spare_words), so the set and its sort need 12 B (the
// spare) + 4 B (the permutation) per particle besides the state in float, where one spare per
// attribute width and four sort words took 52 + 16 B (docs/benchmarks.md "Memory"). No
// allocation once capacity is reached. Kernels must re-fetch attribute pointers after a permute, as before.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/memory/huge_pages.hpp"
#include "core/math/left_cauchy_green.hpp"
#include "core/math/types.hpp"

namespace amalgam {

enum class AttrType { Real, Int32 };

class ParticleSet {
 public:
  using Id = int;

  // Adds an attribute (zero-filled) and returns its id; throws if the name exists.
  Id add(const std::string& name, AttrType type, int width);
  // Id of `name`, or -1.
  Id find(const std::string& name) const;
  // Id of `name`; throws std::out_of_range naming the attribute if absent.
  Id id(const std::string& name) const;

  std::size_t size() const { return n_; }
  void resize(std::size_t n);  // new entries are zero
  int attribute_count() const { return static_cast<int>(attrs_.size()); }
  const std::string& name(Id a) const { return attrs_[a].name; }
  AttrType type(Id a) const { return attrs_[a].type; }
  int width(Id a) const { return attrs_[a].width; }
  // 32-bit words per particle of the spare (a Vec3: 3 in float, 6 in double; >= 3, as the
  // binning's sort uses it for three words per particle).
  static int spare_words_per_particle();
  std::size_t bytes_per_particle() const;        // the attributes plus the permutation's spare
  std::size_t state_bytes_per_particle() const;  // the attributes alone (what a Snapshot copies)

  Real* real(Id a) { return reinterpret_cast<Real*>(attrs_[a].front.data()); }
  const Real* real(Id a) const { return reinterpret_cast<const Real*>(attrs_[a].front.data()); }
  std::int32_t* int32(Id a) { return reinterpret_cast<std::int32_t*>(attrs_[a].front.data()); }
  const std::int32_t* int32(Id a) const {
    return reinterpret_cast<const std::int32_t*>(attrs_[a].front.data());
  }
  Vec3* vec3(Id a) { return reinterpret_cast<Vec3*>(real(a)); }
  const Vec3* vec3(Id a) const { return reinterpret_cast<const Vec3*>(real(a)); }
  Mat3* mat3(Id a) { return reinterpret_cast<Mat3*>(real(a)); }
  const Mat3* mat3(Id a) const { return reinterpret_cast<const Mat3*>(real(a)); }
  SymDev* sym_dev(Id a) { return reinterpret_cast<SymDev*>(real(a)); }
  const SymDev* sym_dev(Id a) const { return reinterpret_cast<const SymDev*>(real(a)); }

  // Raw storage of an attribute: words_per_particle(a) 32-bit words per particle (for I/O).
  int words_per_particle(Id a) const { return attrs_[a].words(); }
  std::uint32_t* words(Id a) { return attrs_[a].front.data(); }
  const std::uint32_t* words(Id a) const { return attrs_[a].front.data(); }

  // The spare, spare_words_per_particle() * size() words, free for a caller's scratch between permutes (its
  // contents are overwritten by permute and compact; pointers are invalidated by them and resize).
  std::uint32_t* spare_words();

  // For every attribute: front[i] = old_front[perm[i]] for i < size().
  void permute(const exec::Space& space, const std::uint32_t* perm);
  // Keeps the m particles index[0 .. m) (increasing: survivors keep their order) and drops the
  // rest: front[i] = old_front[index[i]] for i < m, then size() == m.
  void compact(const exec::Space& space, const std::uint32_t* index, std::size_t m);

  // A copy of every attribute's values (front buffers only: half the set's memory), and its
  // restoration into a set with the same attributes (used to retry a failed frame).
  struct Snapshot {
    std::size_t n = 0;
    std::vector<HugePageVector<std::uint32_t>> words;
  };
  void save(Snapshot& s) const;
  void restore(const Snapshot& s);

 private:
  struct Attr {
    std::string name;
    AttrType type;
    int width;
    HugePageVector<std::uint32_t> front;  // 4-byte words: Real=float uses 1 word, double 2
    int words() const;
  };
  // front[i] = old_front[perm[i]] for i < m, every attribute.
  void gather(const exec::Space& space, const std::uint32_t* perm, std::size_t m);
  std::vector<Attr> attrs_;
  HugePageVector<std::uint32_t> spare_;  // spare_words_per_particle() words per particle
  std::size_t n_ = 0;
};

// The attributes every MPM particle carries, looked up once; `plastic` and `temperature` only
// exist (id >= 0) when a material of the scene needs them (else -1), so elastic scenes do not
// sort or store them. So does C (`affine`): the affine velocity matrix APIC and MLS transfer,
// which is also the velocity gradient a viscous stress reads; a PIC/FLIP run of materials without
// viscosity has none (MpmSolver::keeps_affine: 36 B less per particle in float). So does F_lo
// (`F_low`): a run whose materials are all fluids, whose F is reset to J^{1/3} I with a zero low
// part every substep, has none (MpmSolver::keeps_F_low_part: 36 B less per particle in float).
// Such a run, explicit and Eulerian, keeps no F at all but its determinant J (`volume_only`:
// MpmSolver::keeps_J_only; F = -1, J >= 0): a fluid's state is its volume ratio.
struct MpmAttributes {
  // id: stable particle number; x_lo, F_lo: the low parts of x + x_lo and F + F_lo
  // (core/math/types.hpp: add_compensated; F_lo may be -1, above). No mass: a particle's mass is
  // materials[material].density * volume0 (particle_mass), the float product add_particles
  // stored until checkpoint version 8, so recomputing it is bitwise the stored value.
  ParticleSet::Id x, x_lo, v, F, F_lo = -1, volume0, material, id;
  ParticleSet::Id C = -1, plastic = -1, temperature = -1;
  ParticleSet::Id J = -1;  // J = det F where the run keeps J instead of F (F = -1)
  // b - I of the left Cauchy-Green tensor b = F F^T (6 entries, core/math/left_cauchy_green.hpp)
  // where the run keeps it instead of F and F_lo (F = F_lo = -1; MpmSolver::keeps_b): 24 B
  // instead of 72 in float.
  ParticleSet::Id b = -1;
  // rest: the position a particle had when it was made (set-up or emission; Houdini's `rest`),
  // only when the output asks for it (MpmSolver::keep_rest_positions). An attribute like any
  // other: sorted, migrated between ranks and checkpointed with its particle.
  ParticleSet::Id rest = -1;
  static MpmAttributes add_to(ParticleSet& ps, bool plastic = false, bool temperature = false,
                              bool affine = true, bool F_low = true, bool volume_only = false,
                              bool left_cauchy_green = false);
  static MpmAttributes find_in(const ParticleSet& ps);
};

// Checks of particle state read from outside (a checkpoint): throw InputError naming the
// attribute, the particle and the range. Every Real attribute must be finite; an int32 attribute
// `name`, when the set has it, must lie in [lo, hi] in every component.
void check_finite_attributes(const ParticleSet& ps);
void check_index_attribute(const ParticleSet& ps, const std::string& name, std::int64_t lo,
                           std::int64_t hi);
// Each component of the Real attribute `lo` lies within one ulp of the same component of `hi`
// (a compensated pair, core/math/types.hpp: add_compensated): a larger low part would move the
// state at its next increment.
void check_low_part(const ParticleSet& ps, const std::string& hi, const std::string& lo);
// The 6-entry attribute `name` (when present; b - I, core/math/left_cauchy_green.hpp) makes
// every particle's I + D positive definite, as b = F F^T of an invertible F is.
void check_positive_definite(const ParticleSet& ps, const std::string& name);
// `name` (when present) holds each of 0 .. size()-1 exactly once (particle ids).
void check_permutation_attribute(const ParticleSet& ps, const std::string& name);
// `name` (when present) holds distinct values in [0, limit) (particle ids once particles are
// emitted or removed).
void check_unique_attribute(const ParticleSet& ps, const std::string& name, std::int64_t limit);

}  // namespace amalgam
