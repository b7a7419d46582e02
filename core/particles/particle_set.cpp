#include "core/particles/particle_set.hpp"

#include <cmath>
#include <algorithm>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <vector>

#include "core/errors.hpp"

namespace amalgam {
namespace {
// The spare's width in 32-bit words: a Vec3, so Vec3 attributes (x, x_lo, v) are gathered into
// it and swapped, a Mat3 (C, F, F_lo) is gathered a Vec3-wide group at a time in four passes
// (each copies the last group back while gathering the next) and a scalar is gathered and
// copied back. A Mat3-wide spare (36 B instead of 12 in float) makes a permutation ~1.5x
// faster; it paid while the particles were sorted every substep, not since they are sorted only
// when one leaves its bin's dilated block (sort "when_needed", every ~10-40 substeps; measured
// in docs/benchmarks.md "Memory").
constexpr int kSpareWords = 3 * int(sizeof(Real) / 4);
}  // namespace

int ParticleSet::spare_words_per_particle() {
  return kSpareWords;
}

int ParticleSet::Attr::words() const {
  const int scalar_words = (type == AttrType::Real) ? int(sizeof(Real) / 4) : 1;
  return width * scalar_words;
}

ParticleSet::Id ParticleSet::add(const std::string& name, AttrType type, int width) {
  if (find(name) >= 0)
    throw std::invalid_argument("particle attribute '" + name + "' already exists");
  if (width < 1) throw std::invalid_argument("particle attribute '" + name + "' needs width >= 1");
  Attr a{name, type, width, {}};
  a.front.assign(n_ * size_t(a.words()), 0u);
  attrs_.push_back(std::move(a));
  return Id(attrs_.size() - 1);
}

ParticleSet::Id ParticleSet::find(const std::string& name) const {
  for (size_t i = 0; i < attrs_.size(); ++i)
    if (attrs_[i].name == name) return Id(i);
  return -1;
}

ParticleSet::Id ParticleSet::id(const std::string& name) const {
  const Id a = find(name);
  if (a < 0) throw std::out_of_range("particle attribute '" + name + "' does not exist");
  return a;
}

void ParticleSet::resize(std::size_t n) {
  for (auto& a : attrs_) a.front.resize(n * size_t(a.words()), 0u);
  if (!spare_.empty()) spare_.resize(n * size_t(kSpareWords));
  n_ = n;
}

void ParticleSet::save(Snapshot& s) const {
  s.n = n_;
  s.words.resize(attrs_.size());
  for (size_t a = 0; a < attrs_.size(); ++a) s.words[a] = attrs_[a].front;  // reuses capacity
}

void ParticleSet::restore(const Snapshot& s) {
  if (s.words.size() != attrs_.size())
    throw std::invalid_argument("particle snapshot has a different layout");
  resize(s.n);
  for (size_t a = 0; a < attrs_.size(); ++a) attrs_[a].front = s.words[a];
}

std::size_t ParticleSet::state_bytes_per_particle() const {
  size_t b = 0;
  for (const auto& a : attrs_) b += 4 * size_t(a.words());
  return b;
}

std::size_t ParticleSet::bytes_per_particle() const {
  // The spare a permute creates (counted before the first permute too).
  return state_bytes_per_particle() + 4 * size_t(kSpareWords);
}

std::uint32_t* ParticleSet::spare_words() {
  if (spare_.size() < n_ * size_t(kSpareWords)) spare_.resize(n_ * size_t(kSpareWords));
  return spare_.data();
}

namespace {
// The gather of one attribute of W 32-bit words per particle through a spare of G words per
// particle (W a multiple of G), in place: group g (words gG .. gG+G-1) is gathered into the spare,
// and copied back into the attribute in the pass that gathers group g+1. A pass writes only group
// g-1 of A[i] and reads only group g of A[perm[i]]: no element is read after it is overwritten,
// whatever the permutation, and the passes' iterations are independent. W and G are known at
// compile time, so the copies are a few vector moves.
template <int W, int G>
void gather_in_place(const exec::Space& space, std::size_t n, const std::uint32_t* perm,
                     std::uint32_t* a, std::uint32_t* sp) {
  static_assert(W % G == 0, "whole groups");
  constexpr int groups = W / G;
  for (int g = 0; g <= groups; ++g) {
    exec::parallel_for(space, "particles.permute", exec::Index(n), [=](exec::Index i) {
      std::uint32_t* s = sp + size_t(i) * G;
      if (g > 0) {
        std::uint32_t* d = a + size_t(i) * W + (g - 1) * G;
        for (int k = 0; k < G; ++k) d[k] = s[k];
      }
      if (g < groups) {
        const std::uint32_t* src = a + size_t(perm[i]) * W + g * G;
        for (int k = 0; k < G; ++k) s[k] = src[k];
      }
    });
  }
}
// dst[i] = src[perm[i]] for records of W words (W == the spare's width: the two are swapped).
template <int W>
void gather_records(const exec::Space& space, std::size_t n, const std::uint32_t* perm,
                    const std::uint32_t* src, std::uint32_t* dst) {
  exec::parallel_for(space, "particles.permute", exec::Index(n), [=](exec::Index i) {
    const std::uint32_t* s = src + size_t(perm[i]) * W;
    std::uint32_t* d = dst + size_t(i) * W;
    for (int k = 0; k < W; ++k) d[k] = s[k];
  });
}
// Widths other than those of scalars, Vec3 and Mat3: one word at a time, in place as above.
void gather_words(const exec::Space& space, std::size_t n, const std::uint32_t* perm,
                  std::uint32_t* a, int w, std::uint32_t* sp) {
  for (int g = 0; g <= w; ++g) {
    exec::parallel_for(space, "particles.permute", exec::Index(n), [=](exec::Index i) {
      if (g > 0) a[size_t(i) * size_t(w) + size_t(g - 1)] = sp[i];
      if (g < w) sp[i] = a[size_t(perm[i]) * size_t(w) + size_t(g)];
    });
  }
}
}  // namespace

void ParticleSet::permute(const exec::Space& space, const std::uint32_t* perm) {
  gather(space, perm, n_);
}

void ParticleSet::compact(const exec::Space& space, const std::uint32_t* index, std::size_t m) {
  if (m > n_) throw std::invalid_argument("ParticleSet::compact keeps more particles than it has");
  gather(space, index, m);
  resize(m);
}

void ParticleSet::gather(const exec::Space& space, const std::uint32_t* perm, std::size_t n) {
  constexpr int S = kSpareWords;
  for (auto& a : attrs_) {
    const int w = a.words();
    std::uint32_t* sp = spare_words();
    std::uint32_t* d = a.front.data();
    if (w == S) {  // gather into the spare and swap the two
      gather_records<S>(space, n, perm, d, sp);
      a.front.swap(spare_);  // sizes equal: both hold n_ particles of w words
      continue;
    }
    // The widths of scalars, Vec3 and Mat3 in float and double, narrower than the spare (one
    // group) or a whole number of spares wide.
    if (w == 1)
      gather_in_place<1, 1>(space, n, perm, d, sp);
    else if (w == 2 && S >= 2)
      gather_in_place<2, 2>(space, n, perm, d, sp);
    else if (w == 3 && S >= 3)
      gather_in_place<3, 3>(space, n, perm, d, sp);
    else if (w == 6 && S >= 6)
      gather_in_place<6, 6>(space, n, perm, d, sp);
    else if (w == 6 && S == 3)  // b - I (core/math/left_cauchy_green.hpp) in float
      gather_in_place<6, 3>(space, n, perm, d, sp);
    else if (w == 12 && S == 6)  // b - I in double
      gather_in_place<12, 6>(space, n, perm, d, sp);
    else if (w == 9 && S == 3)
      gather_in_place<9, 3>(space, n, perm, d, sp);
    else if (w == 18 && (S == 6 || S == 9))
      gather_in_place<18, (S == 6 || S == 9) ? S : 1>(space, n, perm, d, sp);
    else
      gather_words(space, n, perm, d, w, sp);
  }
}

MpmAttributes MpmAttributes::add_to(ParticleSet& ps, bool plastic, bool temperature, bool affine,
                                    bool F_low, bool volume_only, bool left_cauchy_green) {
  MpmAttributes m;
  m.x = ps.add("x", AttrType::Real, 3);
  m.x_lo = ps.add("x_lo", AttrType::Real, 3);
  m.v = ps.add("v", AttrType::Real, 3);
  if (affine) m.C = ps.add("C", AttrType::Real, 9);
  if (volume_only) {
    m.F = -1;
    m.J = ps.add("J", AttrType::Real, 1);
  } else if (left_cauchy_green) {
    m.F = -1;
    m.b = ps.add("b", AttrType::Real, 6);
  } else {
    m.F = ps.add("F", AttrType::Real, 9);
    if (F_low) m.F_lo = ps.add("F_lo", AttrType::Real, 9);
  }
  m.volume0 = ps.add("volume0", AttrType::Real, 1);
  m.material = ps.add("material", AttrType::Int32, 1);
  m.id = ps.add("id", AttrType::Int32, 1);
  if (plastic) m.plastic = ps.add("plastic", AttrType::Real, 1);
  if (temperature) m.temperature = ps.add("temperature", AttrType::Real, 1);
  return m;
}

MpmAttributes MpmAttributes::find_in(const ParticleSet& ps) {
  MpmAttributes m;
  m.x = ps.id("x");
  m.x_lo = ps.id("x_lo");
  m.v = ps.id("v");
  m.C = ps.find("C");
  m.F = ps.find("F");
  m.J = ps.find("J");
  m.b = ps.find("b");
  m.F_lo = ps.find("F_lo");
  m.volume0 = ps.id("volume0");
  m.material = ps.id("material");
  m.id = ps.id("id");
  m.plastic = ps.find("plastic");
  m.temperature = ps.find("temperature");
  m.rest = ps.find("rest");
  return m;
}

void check_finite_attributes(const ParticleSet& ps) {
  for (ParticleSet::Id a = 0; a < ps.attribute_count(); ++a) {
    if (ps.type(a) != AttrType::Real) continue;
    const Real* v = ps.real(a);
    const std::size_t w = std::size_t(ps.width(a));
    for (std::size_t k = 0; k < ps.size() * w; ++k)
      if (!std::isfinite(v[k]))
        throw InputError("attribute '" + ps.name(a) + "' of particle " + std::to_string(k / w) +
                         " is not finite");
  }
}

void check_index_attribute(const ParticleSet& ps, const std::string& name, std::int64_t lo,
                           std::int64_t hi) {
  const ParticleSet::Id a = ps.find(name);
  if (a < 0) return;
  const std::int32_t* v = ps.int32(a);
  const std::size_t w = std::size_t(ps.width(a));
  for (std::size_t k = 0; k < ps.size() * w; ++k)
    if (v[k] < lo || v[k] > hi)
      throw InputError("attribute '" + name + "' of particle " + std::to_string(k / w) + " is " +
                       std::to_string(v[k]) + ", outside [" + std::to_string(lo) + ", " +
                       std::to_string(hi) + "]");
}

void check_low_part(const ParticleSet& ps, const std::string& hi, const std::string& lo) {
  const ParticleSet::Id h = ps.find(hi), l = ps.find(lo);
  if (h < 0 || l < 0) return;
  const int w = ps.width(h);
  const Real* a = ps.real(h);
  const Real* b = ps.real(l);
  for (std::size_t i = 0; i < ps.size() * std::size_t(w); ++i)
    if (!(std::abs(b[i]) <= std::numeric_limits<Real>::epsilon() * std::abs(a[i]) ||
          std::abs(b[i]) <= std::numeric_limits<Real>::min()))
      throw InputError("attribute '" + lo + "' of particle " + std::to_string(i / std::size_t(w)) +
                       " is " + std::to_string(b[i]) + ", more than one ulp of '" + hi + "' (" +
                       std::to_string(a[i]) + ")");
}

void check_positive_definite(const ParticleSet& ps, const std::string& name) {
  const ParticleSet::Id a = ps.find(name);
  if (a < 0) return;
  const SymDev* d = ps.sym_dev(a);
  for (std::size_t i = 0; i < ps.size(); ++i) {
    const Mat3 L = b_factor(d[i]);  // finite and with positive pivots iff I + D is SPD
    if (!(L(0, 0) > 0 && L(1, 1) > 0 && L(2, 2) > 0 && L.allFinite()))
      throw InputError("attribute '" + name + "' of particle " + std::to_string(i) +
                       " is not b - I of a positive definite b = F F^T");
  }
}

void check_permutation_attribute(const ParticleSet& ps, const std::string& name) {
  check_unique_attribute(ps, name, std::int64_t(ps.size()));  // n distinct values in [0, n)
}

void check_unique_attribute(const ParticleSet& ps, const std::string& name, std::int64_t limit) {
  const ParticleSet::Id a = ps.find(name);
  if (a < 0) return;
  check_index_attribute(ps, name, 0, limit - 1);
  std::vector<bool> seen(std::size_t(std::max<std::int64_t>(limit, 0)), false);
  const std::int32_t* v = ps.int32(a);
  for (std::size_t i = 0; i < ps.size(); ++i) {
    if (seen[std::size_t(v[i])])
      throw InputError("attribute '" + name + "' of particle " + std::to_string(i) + " repeats " +
                       std::to_string(v[i]));
    seen[std::size_t(v[i])] = true;
  }
}

}  // namespace amalgam
