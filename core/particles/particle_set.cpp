#include "core/particles/particle_set.hpp"

#include <cmath>
#include <algorithm>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <vector>

#include "core/errors.hpp"

namespace amalgam {

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
  for (auto& s : spares_) s.second.resize(n * size_t(s.first));
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
  // One spare per distinct width (those a permute creates; counted before the first permute too).
  std::vector<int> widths;
  for (const auto& a : attrs_)
    if (std::find(widths.begin(), widths.end(), a.words()) == widths.end())
      widths.push_back(a.words());
  size_t b = state_bytes_per_particle();
  for (int w : widths) b += 4 * size_t(w);
  return b;
}

std::vector<std::uint32_t>& ParticleSet::spare(int words, std::size_t n) {
  auto it = std::find_if(spares_.begin(), spares_.end(),
                         [words](const auto& s) { return s.first == words; });
  if (it == spares_.end()) {
    spares_.emplace_back(words, std::vector<std::uint32_t>());
    it = spares_.end() - 1;
  }
  if (it->second.size() < n * size_t(words)) it->second.resize(n * size_t(words));
  return it->second;
}

namespace {
// dst[i] = src[perm[i]] for records of W 32-bit words; W known at compile time so the copy is
// a few vector moves instead of a run-time-length loop.
template <int W>
void gather_records(const exec::Space& space, std::size_t n, const std::uint32_t* perm,
                    const std::uint32_t* src, std::uint32_t* dst) {
  exec::parallel_for(space, "particles.permute", exec::Index(n), [=](exec::Index i) {
    const std::uint32_t* s = src + size_t(perm[i]) * W;
    std::uint32_t* d = dst + size_t(i) * W;
    for (int k = 0; k < W; ++k) d[k] = s[k];
  });
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
  for (auto& a : attrs_) {
    const int w = a.words();
    std::vector<std::uint32_t>& back = spare(w, n_);
    const std::uint32_t* src = a.front.data();
    std::uint32_t* dst = back.data();
    switch (w) {  // the widths of scalars, Vec3 and Mat3 in float and double
      case 1:
        gather_records<1>(space, n, perm, src, dst);
        break;
      case 2:
        gather_records<2>(space, n, perm, src, dst);
        break;
      case 3:
        gather_records<3>(space, n, perm, src, dst);
        break;
      case 6:
        gather_records<6>(space, n, perm, src, dst);
        break;
      case 9:
        gather_records<9>(space, n, perm, src, dst);
        break;
      case 18:
        gather_records<18>(space, n, perm, src, dst);
        break;
      default:
        exec::parallel_for(space, "particles.permute", exec::Index(n), [=](exec::Index i) {
          const std::uint32_t* s = src + size_t(perm[i]) * size_t(w);
          std::uint32_t* d = dst + size_t(i) * size_t(w);
          for (int k = 0; k < w; ++k) d[k] = s[k];
        });
    }
    a.front.swap(back);  // sizes equal: both hold n_ particles of w words
  }
}

MpmAttributes MpmAttributes::add_to(ParticleSet& ps, bool plastic, bool temperature) {
  MpmAttributes m;
  m.x = ps.add("x", AttrType::Real, 3);
  m.x_lo = ps.add("x_lo", AttrType::Real, 3);
  m.v = ps.add("v", AttrType::Real, 3);
  m.C = ps.add("C", AttrType::Real, 9);
  m.F = ps.add("F", AttrType::Real, 9);
  m.F_lo = ps.add("F_lo", AttrType::Real, 9);
  m.mass = ps.add("mass", AttrType::Real, 1);
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
  m.C = ps.id("C");
  m.F = ps.id("F");
  m.F_lo = ps.id("F_lo");
  m.mass = ps.id("mass");
  m.volume0 = ps.id("volume0");
  m.material = ps.id("material");
  m.id = ps.id("id");
  m.plastic = ps.find("plastic");
  m.temperature = ps.find("temperature");
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
