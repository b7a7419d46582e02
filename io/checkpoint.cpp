#include "io/checkpoint.hpp"

#include <cmath>
#include <cstring>
#include <fstream>
#include <functional>
#include <sstream>
#include <vector>

#include "core/errors.hpp"
#include "io/files.hpp"
#include "io/scene.hpp"
#include "io/writers.hpp"

namespace amalgam {

namespace {
constexpr char kMagic[] = "AMALGAM-CKPT\n";
constexpr std::size_t kMagicLen = sizeof(kMagic) - 1;
// 4: MPM positions' and F's low parts (x_lo, F_lo); 5: peridynamic positions' low parts (x_lo);
// 6: the particle count may differ from the scene's initial one (MPM emitters and kill regions,
// whose state follows in section sources.state)
constexpr std::uint32_t kVersion = 6;

template <class T>
void put(std::string& b, const T& v) {
  b.append(reinterpret_cast<const char*>(&v), sizeof(T));
}

class Reader {
 public:
  Reader(const std::string& data, const std::string& path) : d_(data), path_(path) {}
  template <class T>
  T get(const char* what) {
    T v;
    need(sizeof(T), what);
    std::memcpy(&v, d_.data() + pos_, sizeof(T));
    pos_ += sizeof(T);
    return v;
  }
  const char* take(std::size_t n, const char* what) {
    need(n, what);
    const char* p = d_.data() + pos_;
    pos_ += n;
    return p;
  }
  std::size_t pos() const { return pos_; }

 private:
  void need(std::size_t n, const char* what) {
    if (d_.size() - pos_ < n)
      throw InputError(path_ + ": checkpoint is truncated (ends inside " + what + " at byte " +
                       std::to_string(pos_) + " of " + std::to_string(d_.size()) + ")");
  }
  const std::string& d_;
  const std::string& path_;
  std::size_t pos_ = 0;
};
using Section = StateSection;

void write_state(const std::string& path, const ParticleSet& ps, double time, std::uint64_t steps,
                 int next_frame, int retries, std::uint64_t scene_fingerprint,
                 const std::vector<Section>& sections) {
  std::string b;
  std::size_t total = 128;
  for (int a = 0; a < ps.attribute_count(); ++a)
    total += 64 + ps.size() * 4 * size_t(ps.words_per_particle(a));
  for (const Section& sec : sections) total += 64 + sec.bytes;
  b.reserve(total);
  b.append(kMagic, kMagicLen);
  put(b, kVersion);
  put(b, std::uint32_t(sizeof(Real)));
  put(b, scene_fingerprint);
  put(b, time);
  put(b, steps);
  put(b, std::int32_t(next_frame));
  put(b, std::int32_t(retries));
  put(b, std::uint64_t(ps.size()));
  put(b, std::uint32_t(ps.attribute_count()));
  for (int a = 0; a < ps.attribute_count(); ++a) {
    const std::string& name = ps.name(a);
    put(b, std::uint32_t(name.size()));
    b.append(name);
    put(b, std::uint32_t(ps.type(a)));
    put(b, std::uint32_t(ps.width(a)));
    put(b, std::uint32_t(ps.words_per_particle(a)));
    b.append(reinterpret_cast<const char*>(ps.words(a)),
             ps.size() * 4 * size_t(ps.words_per_particle(a)));
  }
  put(b, std::uint32_t(sections.size()));
  for (const Section& sec : sections) {
    put(b, std::uint32_t(sec.name.size()));
    b.append(sec.name);
    put(b, std::uint64_t(sec.bytes));
    b.append(sec.data, sec.bytes);
  }
  put(b, fnv1a64(b.data(), b.size()));
  write_file_atomic(path, b);
}

// Reads into ps (same attribute layout) and the sections (same names and sizes, in order).
// `max_particles`: the most particles the run can hold when its count varies (emitters, kill
// regions), else 0 (the checkpoint must hold exactly ps.size()).
CheckpointState read_state(const std::string& path, ParticleSet& ps,
                           std::uint64_t scene_fingerprint, const std::vector<Section>& sections,
                           std::size_t max_particles) {
  // Never more than the memory there is (a hostile size would end in bad_alloc).
  const std::uint64_t avail = available_memory_bytes();
  const std::string d =
      read_input_file(path, "checkpoint", avail > 0 ? avail : std::uint64_t(1) << 40);
  if (d.size() < kMagicLen || std::memcmp(d.data(), kMagic, kMagicLen) != 0)
    throw InputError(path + ": not an Amalgam checkpoint (bad magic)");
  if (d.size() < kMagicLen + 8) throw InputError(path + ": checkpoint is truncated (no checksum)");
  std::uint64_t stored = 0;
  std::memcpy(&stored, d.data() + d.size() - 8, 8);
  if (fnv1a64(d.data(), d.size() - 8) != stored)
    throw InputError(path + ": checkpoint is corrupt or truncated (checksum mismatch)");
  Reader r(d, path);
  r.take(kMagicLen, "magic");
  const auto version = r.get<std::uint32_t>("version");
  if (version < 1 || version > kVersion)
    throw InputError(path + ": checkpoint format version " + std::to_string(version) +
                     ", this build reads 1 to " + std::to_string(kVersion));
  const auto real_size = r.get<std::uint32_t>("precision");
  if (real_size != sizeof(Real))
    throw InputError(path + ": checkpoint was written by a " +
                     (real_size == 8 ? "double" : "float") + " build, this build is " +
                     real_name());
  const auto fp = r.get<std::uint64_t>("scene fingerprint");
  if (fp != scene_fingerprint)
    throw InputError(
        path + ": checkpoint was written for a different scene (or the scene file changed since)");
  CheckpointState st;
  st.time = r.get<double>("time");
  st.steps = r.get<std::uint64_t>("step count");
  st.next_frame = r.get<std::int32_t>("frame");
  st.retries = version >= 3 ? r.get<std::int32_t>("retries") : 0;
  if (st.retries < 0 || st.retries > kMaxRetries)
    throw InputError(path + ": checkpoint field 'retries' is " + std::to_string(st.retries) +
                     ", outside [0, " + std::to_string(kMaxRetries) + "]");
  // The checksum only says the file is what was written: the header is still checked against
  // the scene before anything is sized by it.
  if (!std::isfinite(st.time) || st.time < 0 || st.time > 1e12)
    throw InputError(path + ": checkpoint field 'time' is " + std::to_string(st.time) +
                     ", outside [0, 1e12] s");
  if (st.next_frame < 1 || st.next_frame > kMaxFrames + 1)
    throw InputError(path + ": checkpoint field 'frame' is " + std::to_string(st.next_frame) +
                     ", outside [1, " + std::to_string(kMaxFrames + 1) + "]");
  if ((st.steps == 0) != (st.time == 0))
    throw InputError(path + ": checkpoint fields 'step count' (" + std::to_string(st.steps) +
                     ") and 'time' (" + std::to_string(st.time) + ") disagree");
  const auto n = r.get<std::uint64_t>("particle count");
  const auto nattr = r.get<std::uint32_t>("attribute count");
  // Before version 4 MPM particles had no low parts of x and F, before version 5 peridynamic
  // particles none of x (core/math/types.hpp: add_compensated): an older checkpoint resumes with
  // them zero. (Peridynamic particles have x0, MPM particles do not.)
  std::vector<int> missing;
  const bool pd = ps.find("x0") >= 0;
  if (version < 4 || (version < 5 && pd))
    for (const char* lo : {"x_lo", "F_lo"})
      if (ps.find(lo) >= 0) missing.push_back(ps.find(lo));
  const std::uint32_t nmissing = std::uint32_t(missing.size());
  if (nattr + nmissing != std::uint32_t(ps.attribute_count()))
    throw InputError(path + ": checkpoint has " + std::to_string(nattr) +
                     " particle attributes, expected " +
                     std::to_string(ps.attribute_count() - int(nmissing)));
  if (max_particles > 0 && version >= 6) {  // checked before anything is sized by it
    if (n > max_particles)
      throw InputError(path + ": checkpoint field 'particle count' is " + std::to_string(n) +
                       ", above the " + std::to_string(max_particles) +
                       " particles this scene can hold (its objects and emitters)");
    ps.resize(std::size_t(n));
  }
  if (n != ps.size())
    throw InputError(path + ": checkpoint field 'particle count' is " + std::to_string(n) +
                     ", this scene has " + std::to_string(ps.size()) + " particles");
  for (std::uint32_t i = 0; i < nattr; ++i) {
    const auto len = r.get<std::uint32_t>("attribute name length");
    if (len > 256) throw InputError(path + ": checkpoint attribute name too long (corrupt file)");
    const std::string name(r.take(len, "attribute name"), len);
    const int a = ps.find(name);
    const auto type = r.get<std::uint32_t>("attribute type");
    const auto width = r.get<std::uint32_t>("attribute width");
    const auto words = r.get<std::uint32_t>("attribute words");
    if (a < 0 || type != std::uint32_t(ps.type(a)) || width != std::uint32_t(ps.width(a)) ||
        words != std::uint32_t(ps.words_per_particle(a)))
      throw InputError(path + ": checkpoint attribute '" + name +
                       "' does not match this solver's layout");
    const std::size_t bytes = size_t(n) * 4 * words;
    const char* src = r.take(bytes, "attribute data");
    if (bytes > 0) std::memcpy(ps.words(a), src, bytes);
  }
  for (const int a : missing)
    if (ps.size() > 0)
      std::memset(ps.words(a), 0, ps.size() * 4 * std::size_t(ps.words_per_particle(a)));
  const std::uint32_t nsec = version >= 2 ? r.get<std::uint32_t>("section count") : 0;
  if (nsec != sections.size())
    throw InputError(path + ": checkpoint has " + std::to_string(nsec) +
                     " state sections, this solver expects " + std::to_string(sections.size()) +
                     " (written by a different method?)");
  for (const Section& sec : sections) {
    const auto len = r.get<std::uint32_t>("section name length");
    if (len > 256) throw InputError(path + ": checkpoint section name too long (corrupt file)");
    const std::string name(r.take(len, "section name"), len);
    const auto bytes = r.get<std::uint64_t>("section size");
    if (name != sec.name || (!sec.resize && bytes != sec.bytes))
      throw InputError(path + ": checkpoint section '" + name + "' (" + std::to_string(bytes) +
                       " bytes) does not match this solver's '" + sec.name + "' (" +
                       std::to_string(sec.bytes) + ")");
    const char* src = r.take(std::size_t(bytes), "section data");
    char* dst = sec.data;
    if (sec.resize) {
      try {
        dst = sec.resize(bytes);
      } catch (const InputError& e) {
        throw InputError(path + ": " + e.what());
      }
    }
    if (bytes > 0) std::memcpy(dst, src, std::size_t(bytes));  // an empty section's dst is null
  }
  if (r.pos() != d.size() - 8)
    throw InputError(path + ": checkpoint has trailing bytes (corrupt file)");
  return st;
}

}  // namespace

void write_checkpoint(const std::string& path, Simulation& sim, int next_frame,
                      std::uint64_t scene_fingerprint, int retries) {
  write_state(path, sim.particles(), sim.time(), sim.step_count(), next_frame, retries,
              scene_fingerprint, sim.checkpoint_sections());
}

CheckpointState read_checkpoint(const std::string& path, Simulation& sim,
                                std::uint64_t scene_fingerprint) {
  const CheckpointState st =
      read_state(path, sim.particles(), scene_fingerprint, sim.restore_sections(),
                 sim.variable_particle_count() ? sim.max_particle_count() : 0);
  try {
    sim.restored(st.time, st.steps);
  } catch (const InputError& e) {
    throw InputError(path + ": " + e.what());
  }
  return st;
}

}  // namespace amalgam
