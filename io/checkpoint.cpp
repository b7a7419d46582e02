#include "io/checkpoint.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <nlohmann/json.hpp>
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
// whose state follows in section sources.state); 7: per-rank checkpoints (a manifest naming one
// part per rank, each a version-7 file of the rank's particles with their order keys in section
// dist.order; a single file is laid out as version 6); 8: MPM particles store no mass (it is
// density x volume0, MaterialParams::mass; an older file's "mass" is skipped on reading, as it
// always held that product)
constexpr std::uint32_t kVersion = 8;
constexpr char kOrderSection[] = "dist.order";
constexpr char kOptionalAttribute[] = "rest";
// MPM's affine matrix: only APIC, MLS and viscous materials keep it (MpmSolver::keeps_affine). A
// file written by a run that kept it (an older binary's PIC/FLIP run) is read by one that does
// not with C skipped (it was never read); a run that needs C refuses a file without it.
constexpr char kAffineAttribute[] = "C";
// F's low part: a run whose materials are all fluids keeps none (MpmSolver::keeps_F_low_part). A
// file written by a run that kept it (an older binary's) is read by one that does not with F_lo
// skipped (such a run's low parts are zero at every substep's end); a run that keeps it refuses
// a file of version >= 4 without it (no binary writes one), naming the attribute.
constexpr char kLowPartAttribute[] = "F_lo";
// A run whose materials are all fluids keeps J = det F instead of F (MpmSolver::keeps_J_only). A
// file written by a run that kept F (an older binary's) is read by one that keeps J with
// J = det F, the J its next substep's stress would have read from F.
constexpr char kVolumeAttribute[] = "J";
// A run that keeps b - I of b = F F^T instead of F and F_lo (MpmSolver::keeps_b) reads a file
// holding F (and F_lo) with b - I = (F + F_lo)(F + F_lo)^T - I, rounded once; a run keeping F
// refuses a file holding b (the rotation of F is not in it), naming it. No new version: the
// attribute list names what a file holds.
constexpr char kLeftCauchyGreenAttribute[] = "b";

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

// A checkpoint streamed to its file with its FNV-1a checksum kept as the bytes pass: it is
// never built in memory as one string (a copy of the whole state, whose fresh pages cost more
// than the write on this project's VMs: docs/benchmarks.md, "Checkpoints streamed, the
// diagnostics' energies at the vector width, b's update in one register").
class FileSink {
 public:
  explicit FileSink(TempFile& f) : f_(f) { buf_.reserve(kBuffer); }
  void append(const char* p, std::size_t n) {
    h_ = fnv1a64(p, n, h_);
    bytes_ += n;
    if (n >= kBuffer / 4) {  // an attribute's array: written from where it lies
      flush();
      f_.write(p, n);
      return;
    }
    buf_.append(p, n);
    if (buf_.size() >= kBuffer) flush();
  }
  std::uint64_t finish() {
    const std::uint64_t h = h_;
    append(reinterpret_cast<const char*>(&h), 8);
    flush();
    return h;
  }
  void append(const std::string& s) { append(s.data(), s.size()); }
  std::uint64_t bytes() const { return bytes_; }
  // After finish(): FNV-1a of the whole file, its checksum included (a part's record in the
  // manifest): the running hash carried over the checksum's 8 bytes.
  std::uint64_t whole_checksum() const { return h_; }

 private:
  void flush() {
    f_.write(buf_.data(), buf_.size());
    buf_.clear();
  }
  static constexpr std::size_t kBuffer = 1 << 16;
  TempFile& f_;
  std::string buf_;
  std::uint64_t h_ = fnv1a64(nullptr, 0);
  std::uint64_t bytes_ = 0;
};

template <class Sink, class T>
void put(Sink& b, const T& v) {
  b.append(reinterpret_cast<const char*>(&v), sizeof(T));
}
// The checkpoint's bytes (format in io/checkpoint.hpp), checksum last; returns the checksum.
std::uint64_t emit_state(FileSink& b, const ParticleSet& ps, double time, std::uint64_t steps,
                         int next_frame, int retries, std::uint64_t scene_fingerprint,
                         const std::vector<Section>& sections) {
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
  return b.finish();
}

// Reads into ps (same attribute layout) and the sections (same names and sizes, in order).
// `max_particles`: the most particles the run can hold when its count varies (emitters, kill
// regions), else 0 (the checkpoint must hold exactly ps.size()).
CheckpointState read_state(const std::string& path, const std::string& d, ParticleSet& ps,
                           std::uint64_t scene_fingerprint, const std::vector<Section>& sections,
                           std::size_t max_particles) {
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
  // Before version 8 MPM particles stored their mass (dropped: it is recomputed).
  const std::uint32_t ndropped = version < 8 && ps.find("volume0") >= 0 ? 1 : 0;
  // `rest` (MPM: kept only when the output asks for it, and the output is not part of the scene's
  // fingerprint) may be in the file and not in this run, which skips it, or in this run and not in
  // the file, which the simulation then fills (Simulation::fill_absent_attribute). MPM's `C` may
  // be in the file and not in this run (skipped: kAffineAttribute); one absent from the file but
  // needed by this run is refused below by name.
  const bool rest = ps.find(kOptionalAttribute) >= 0;
  const bool affine = ps.find(kAffineAttribute) >= 0;
  const bool skip_affine = !pd && !affine;
  const int low_part = pd ? -1 : ps.find(kLowPartAttribute);
  const bool skip_low_part = !pd && low_part < 0;
  const int volume = pd ? -1 : ps.find(kVolumeAttribute);
  const bool F_to_J = volume >= 0 && ps.find("F") < 0;
  const int left_cg = pd ? -1 : ps.find(kLeftCauchyGreenAttribute);
  std::vector<Mat3> F_in, F_lo_in;  // F_to_b: the file's F and F_lo
  const std::uint32_t expected = std::uint32_t(ps.attribute_count()) - nmissing + ndropped;
  const std::uint32_t fewest = expected - (rest ? 1 : 0) - (affine ? 1 : 0);
  const std::uint32_t most = expected + (rest ? 0 : 1) + (skip_affine ? 1 : 0) +
                             (skip_low_part && left_cg < 0 ? 1 : 0) + (left_cg >= 0 ? 1 : 0);
  if (nattr < fewest || nattr > most)
    throw InputError(path + ": checkpoint has " + std::to_string(nattr) +
                     " particle attributes, expected " + std::to_string(expected));
  std::vector<char> read(std::size_t(ps.attribute_count()), 0);
  for (const int a : missing) read[std::size_t(a)] = 1;
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
    if (ndropped && name == "mass" && a < 0 && type == std::uint32_t(AttrType::Real) &&
        width == 1 && words == std::uint32_t(sizeof(Real) / 4)) {
      r.take(size_t(n) * 4 * words, "attribute data");
      continue;
    }
    if (name == kOptionalAttribute && a < 0 && type == std::uint32_t(AttrType::Real) &&
        width == 3 && words == std::uint32_t(3 * sizeof(Real) / 4)) {
      r.take(size_t(n) * 4 * words, "attribute data");
      continue;
    }
    if (left_cg >= 0 && (name == "F" || name == kLowPartAttribute) && a < 0 &&
        type == std::uint32_t(AttrType::Real) && width == 9 &&
        words == std::uint32_t(9 * sizeof(Real) / 4)) {
      std::vector<Mat3>& dst = name == "F" ? F_in : F_lo_in;
      if (!dst.empty() || read[std::size_t(left_cg)])
        throw InputError(path + ": checkpoint attribute '" + name +
                         "' appears twice or beside 'b'");
      dst.resize(std::size_t(n));
      const char* src = r.take(size_t(n) * 4 * words, "attribute data");
      if (n > 0) std::memcpy(static_cast<void*>(dst.data()), src, size_t(n) * sizeof(Mat3));
      continue;
    }
    if (name == kLeftCauchyGreenAttribute && a < 0 && !pd)
      throw InputError(path +
                       ": checkpoint holds 'b' (b = F F^T, written by a run that kept no F), "
                       "but this run keeps F itself (its output asks for 'F'): resume without "
                       "'F' in output.attributes");
    if (((skip_affine && name == kAffineAttribute) ||
         (skip_low_part && name == kLowPartAttribute)) &&
        a < 0 && type == std::uint32_t(AttrType::Real) && width == 9 &&
        words == std::uint32_t(9 * sizeof(Real) / 4)) {
      r.take(size_t(n) * 4 * words, "attribute data");
      continue;
    }
    if (F_to_J && name == "F" && a < 0 && type == std::uint32_t(AttrType::Real) && width == 9 &&
        words == std::uint32_t(9 * sizeof(Real) / 4)) {
      const char* src = r.take(size_t(n) * 4 * words, "attribute data");
      if (read[std::size_t(volume)])
        throw InputError(path + ": checkpoint attributes 'F' and 'J' both hold the volume ratio");
      Real* J = ps.real(volume);
      for (std::size_t i = 0; i < std::size_t(n); ++i) {
        Mat3 F;
        std::memcpy(F.data(), src + i * sizeof(Mat3), sizeof(Mat3));
        J[i] = F.determinant();
      }
      read[std::size_t(volume)] = 1;
      continue;
    }
    if (a < 0 || type != std::uint32_t(ps.type(a)) || width != std::uint32_t(ps.width(a)) ||
        words != std::uint32_t(ps.words_per_particle(a)))
      throw InputError(path + ": checkpoint attribute '" + name +
                       "' does not match this solver's layout");
    const std::size_t bytes = size_t(n) * 4 * words;
    const char* src = r.take(bytes, "attribute data");
    if (bytes > 0) std::memcpy(ps.words(a), src, bytes);
    if (read[std::size_t(a)])
      throw InputError(path +
                       (a == volume && F_to_J
                            ? ": checkpoint attributes 'F' and 'J' both hold the volume ratio"
                            : ": checkpoint attribute '" + name + "' appears twice"));
    read[std::size_t(a)] = 1;
  }
  if (!F_lo_in.empty() && F_in.empty())
    throw InputError(path + ": checkpoint has 'F_lo' without 'F'");
  if (!F_in.empty()) {  // F (+ F_lo) -> b - I
    if (read[std::size_t(left_cg)])
      throw InputError(path + ": checkpoint attributes 'F' and 'b' both hold the deformation");
    SymDev* b = ps.sym_dev(left_cg);
    for (std::size_t i = 0; i < std::size_t(n); ++i) {
      Eigen::Matrix3d F = F_in[i].cast<double>();
      if (!F_lo_in.empty()) F += F_lo_in[i].cast<double>();
      b[i] = b_from_F<Real>(F);
    }
    read[std::size_t(left_cg)] = 1;
  }
  for (int a = 0; a < ps.attribute_count(); ++a) {
    if (read[std::size_t(a)]) continue;
    if (a == low_part)  // no binary since version 4 writes a file without F_lo for a run keeping it
      throw InputError(path + ": checkpoint has no particle attribute '" + ps.name(a) +
                       "' (the low part of F this run keeps for its solid materials)");
    if (ps.name(a) == kAffineAttribute && !pd)
      throw InputError(path + ": checkpoint has no particle attribute '" + ps.name(a) +
                       "' (the affine velocity matrix this run's APIC/MLS transfer or viscous "
                       "material needs; a PIC/FLIP run without viscosity writes none)");
    if (ps.name(a) != kOptionalAttribute)
      throw InputError(path + ": checkpoint has no particle attribute '" + ps.name(a) + "'");
    st.absent.push_back(ps.name(a));
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

// A part of a per-rank checkpoint, parsed (pointers into its bytes).
struct ParsedPart {
  std::uint32_t version = 0, real_size = 0;
  std::uint64_t fingerprint = 0, steps = 0, n = 0;
  double time = 0;
  std::int32_t frame = 0, retries = 0;
  struct Attr {
    std::string name;
    std::uint32_t type = 0, width = 0, words = 0;
    const char* data = nullptr;
  };
  struct Sec {
    std::string name;
    std::uint64_t bytes = 0;
    const char* data = nullptr;
  };
  std::vector<Attr> attrs;
  std::vector<Sec> secs;
};

ParsedPart parse_part(const std::string& path, const std::string& d) {
  if (d.size() < kMagicLen + 8 || std::memcmp(d.data(), kMagic, kMagicLen) != 0)
    throw InputError(path + ": not an Amalgam checkpoint (bad magic)");
  std::uint64_t stored = 0;
  std::memcpy(&stored, d.data() + d.size() - 8, 8);
  if (fnv1a64(d.data(), d.size() - 8) != stored)
    throw InputError(path + ": checkpoint is corrupt or truncated (checksum mismatch)");
  Reader r(d, path);
  r.take(kMagicLen, "magic");
  // A length-prefixed name of at most 256 bytes.
  auto read_name = [&](const std::string& what) {
    const auto len = r.get<std::uint32_t>((what + " name length").c_str());
    if (len > 256)
      throw InputError(path + ": checkpoint " + what + " name too long (corrupt file)");
    return std::string(r.take(len, (what + " name").c_str()), len);
  };
  ParsedPart p;
  p.version = r.get<std::uint32_t>("version");
  if (p.version != kVersion)
    throw InputError(path + ": checkpoint part of format version " + std::to_string(p.version) +
                     ", expected " + std::to_string(kVersion));
  p.real_size = r.get<std::uint32_t>("precision");
  p.fingerprint = r.get<std::uint64_t>("scene fingerprint");
  p.time = r.get<double>("time");
  p.steps = r.get<std::uint64_t>("step count");
  p.frame = r.get<std::int32_t>("frame");
  p.retries = r.get<std::int32_t>("retries");
  p.n = r.get<std::uint64_t>("particle count");
  if (p.n > d.size()) throw InputError(path + ": checkpoint field 'particle count' is corrupt");
  const auto nattr = r.get<std::uint32_t>("attribute count");
  if (nattr > 256) throw InputError(path + ": checkpoint attribute count is corrupt");
  for (std::uint32_t i = 0; i < nattr; ++i) {
    ParsedPart::Attr a;
    a.name = read_name("attribute");
    a.type = r.get<std::uint32_t>("attribute type");
    a.width = r.get<std::uint32_t>("attribute width");
    a.words = r.get<std::uint32_t>("attribute words");
    if (a.words > 64) throw InputError(path + ": checkpoint attribute words are corrupt");
    a.data = r.take(std::size_t(p.n) * 4 * a.words, "attribute data");
    p.attrs.push_back(a);
  }
  const auto nsec = r.get<std::uint32_t>("section count");
  if (nsec > 4096) throw InputError(path + ": checkpoint section count is corrupt");
  for (std::uint32_t i = 0; i < nsec; ++i) {
    ParsedPart::Sec sec;
    sec.name = read_name("section");
    sec.bytes = r.get<std::uint64_t>("section size");
    if (sec.bytes > d.size()) throw InputError(path + ": checkpoint section size is corrupt");
    sec.data = r.take(std::size_t(sec.bytes), "section data");
    p.secs.push_back(sec);
  }
  if (r.pos() != d.size() - 8)
    throw InputError(path + ": checkpoint has trailing bytes (corrupt file)");
  if (p.secs.empty() || p.secs[0].name != kOrderSection || p.secs[0].bytes != 16 * p.n)
    throw InputError(path + ": checkpoint part has no section " + kOrderSection +
                     " of 16 bytes per particle");
  return p;
}

std::string hex64(std::uint64_t v) {
  char s[20];
  std::snprintf(s, sizeof s, "%016llx", (unsigned long long)v);
  return s;
}

std::string dir_of(const std::string& path) {
  const std::size_t slash = path.find_last_of('/');
  return slash == std::string::npos ? "." : path.substr(0, slash);
}

}  // namespace

std::string checkpoint_part_name(std::uint64_t generation, int rank) {
  char s[64];
  std::snprintf(s, sizeof s, "checkpoint.g%06llu.r%03d.amck", (unsigned long long)generation, rank);
  return s;
}

bool is_checkpoint_manifest(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  char c = 0;
  return in.get(c) && c == '{';
}

std::string join_checkpoint(const std::string& manifest_path, const JoinSlice& slice,
                            std::vector<std::uint64_t>* keys, std::uint64_t* total) {
  const std::string text = read_input_file(manifest_path, "checkpoint manifest", 1 << 26);
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(text);
  } catch (const nlohmann::json::exception& e) {
    throw InputError(manifest_path + ": checkpoint manifest is not valid JSON: " + e.what());
  }
  const std::string dir = dir_of(manifest_path);
  std::vector<std::string> bytes;
  std::vector<ParsedPart> parts;
  std::vector<char> rows_of;  // per part read: whether its particles join (its slice's)
  std::uint64_t listed = 0;   // the manifest's particle count over every part
  std::string key;
  try {
    auto at = [&](const nlohmann::json& o, const std::string& where, const char* k) {
      key = where + "/" + k;
      return o.at(k);
    };
    if (at(j, "", "format").get<std::string>() != "amalgam-checkpoint-parts" ||
        at(j, "", "version").get<int>() != 1)
      throw InputError(manifest_path + ": " + key + ": not an Amalgam checkpoint manifest");
    const int ranks = at(j, "", "ranks").get<int>();
    const nlohmann::json& list = at(j, "", "parts");
    if (ranks < 1 || ranks > 1 << 20 || !list.is_array() || list.size() != std::size_t(ranks))
      throw InputError(manifest_path + ": /parts: expected one part per rank (" +
                       std::to_string(ranks) + ")");
    for (int r = 0; r < ranks; ++r) {
      const std::string w = "/parts/" + std::to_string(r);
      const nlohmann::json& e = list[std::size_t(r)];
      const std::uint64_t listed_here = at(e, w, "particles").get<std::uint64_t>();
      if (listed_here > (std::uint64_t(1) << 40))
        throw InputError(manifest_path + ": " + key + ": " + std::to_string(listed_here) +
                         " particles is not a count");
      listed += listed_here;
      const bool mine = r % slice.parts == slice.part;
      if (!mine && r > 0) continue;  // another rank's slice
      rows_of.push_back(mine);
      const std::string file = at(e, w, "file").get<std::string>();
      if (file.empty() || file.find('/') != std::string::npos || file[0] == '.')
        throw InputError(manifest_path + ": " + key + ": '" + file +
                         "' is not a file name in the checkpoint's directory");
      const std::uint64_t size = at(e, w, "bytes").get<std::uint64_t>();
      const std::string sum = at(e, w, "fnv1a64").get<std::string>();
      const std::string path = dir + "/" + file;
      const std::string whose = " (checkpoint part of rank " + std::to_string(r) + " of " +
                                std::to_string(ranks) + ", listed in " + manifest_path + ")";
      try {
        const std::uint64_t avail = available_memory_bytes();
        bytes.push_back(
            read_input_file(path, "checkpoint part", avail > 0 ? avail : std::uint64_t(1) << 40));
        if (bytes.back().size() != size ||
            hex64(fnv1a64(bytes.back().data(), bytes.back().size())) != sum)
          throw InputError(path +
                           ": does not match its manifest (size or checksum): the part "
                           "is corrupt, truncated or from another checkpoint");
        parts.push_back(parse_part(path, bytes.back()));
      } catch (const InputError& err) {
        throw InputError(err.what() + whose);
      }
      const ParsedPart& p = parts.back();
      const ParsedPart& p0 = parts.front();
      bool same = p.real_size == p0.real_size && p.fingerprint == p0.fingerprint &&
                  p.time == p0.time && p.steps == p0.steps && p.frame == p0.frame &&
                  p.retries == p0.retries && p.attrs.size() == p0.attrs.size();
      for (std::size_t a = 0; same && a < p.attrs.size(); ++a)
        same = p.attrs[a].name == p0.attrs[a].name && p.attrs[a].type == p0.attrs[a].type &&
               p.attrs[a].width == p0.attrs[a].width && p.attrs[a].words == p0.attrs[a].words;
      if (!same || (r > 0 && p.secs.size() != 1))
        throw InputError(path + ": its header, attributes or sections do not match rank 0's part" +
                         whose);
      if (at(e, w, "particles").get<std::uint64_t>() != p.n)
        throw InputError(path + ": holds " + std::to_string(p.n) +
                         " particles, the manifest says otherwise" + whose);
    }
  } catch (const nlohmann::json::exception& e) {
    throw InputError(manifest_path + ": " + key + ": missing or of the wrong type (" + e.what() +
                     ")");
  }
  // The single process's order: every particle by its two keys.
  struct Row {
    std::uint64_t k0, k1;
    std::uint32_t part, index;
    bool operator<(const Row& o) const { return k0 != o.k0 ? k0 < o.k0 : k1 < o.k1; }
  };
  std::vector<Row> rows;
  for (std::size_t r = 0; r < parts.size(); ++r)
    for (std::uint64_t i = 0; rows_of[r] && i < parts[r].n; ++i) {
      std::uint64_t k[2];
      std::memcpy(k, parts[r].secs[0].data + 16 * i, 16);
      rows.push_back({k[0], k[1], std::uint32_t(r), std::uint32_t(i)});
    }
  std::sort(rows.begin(), rows.end());
  if (keys) {
    keys->resize(2 * rows.size());
    for (std::size_t i = 0; i < rows.size(); ++i)
      (*keys)[2 * i] = rows[i].k0, (*keys)[2 * i + 1] = rows[i].k1;
  }
  if (total) *total = listed;
  const ParsedPart& p0 = parts.front();
  std::string b;
  b.append(kMagic, kMagicLen);
  put(b, kVersion);
  put(b, p0.real_size);
  put(b, p0.fingerprint);
  put(b, p0.time);
  put(b, p0.steps);
  put(b, p0.frame);
  put(b, p0.retries);
  put(b, std::uint64_t(rows.size()));
  put(b, std::uint32_t(p0.attrs.size()));
  for (std::size_t a = 0; a < p0.attrs.size(); ++a) {
    put(b, std::uint32_t(p0.attrs[a].name.size()));
    b.append(p0.attrs[a].name);
    put(b, p0.attrs[a].type);
    put(b, p0.attrs[a].width);
    put(b, p0.attrs[a].words);
    const std::size_t w = 4 * std::size_t(p0.attrs[a].words);
    for (const Row& row : rows) b.append(parts[row.part].attrs[a].data + w * row.index, w);
  }
  put(b, std::uint32_t(p0.secs.size() - 1));
  for (std::size_t k = 1; k < p0.secs.size(); ++k) {
    put(b, std::uint32_t(p0.secs[k].name.size()));
    b.append(p0.secs[k].name);
    put(b, p0.secs[k].bytes);
    b.append(p0.secs[k].data, std::size_t(p0.secs[k].bytes));
  }
  put(b, fnv1a64(b.data(), b.size()));
  return b;
}

CheckpointPartRecord write_checkpoint_part(const std::string& dir, std::uint64_t generation,
                                           int rank, Simulation& sim, int next_frame,
                                           std::uint64_t scene_fingerprint, int retries,
                                           const exec::Space& space) {
  const Simulation::RankPart part = sim.my_part();
  const ParticleSet& all = sim.my_particles();
  ParticleSet kept;
  const ParticleSet* ps = &all;
  if (!part.all) {
    kept = all;
    kept.compact(space, part.rows.data(), part.rows.size());
    ps = &kept;
  }
  std::vector<Section> sections = {
      {kOrderSection, const_cast<char*>(reinterpret_cast<const char*>(part.order.data())),
       part.order.size() * sizeof(std::uint64_t)}};
  if (rank == 0)
    for (const Section& s : sim.checkpoint_sections()) sections.push_back(s);
  CheckpointPartRecord rec;
  rec.file = checkpoint_part_name(generation, rank);
  rec.particles = ps->size();
  TempFile tmp(dir + "/" + rec.file);
  FileSink sink(tmp);
  emit_state(sink, *ps, sim.time(), sim.step_count(), next_frame, retries, scene_fingerprint,
             sections);
  rec.bytes = sink.bytes();
  rec.checksum = sink.whole_checksum();
  tmp.commit();
  return rec;
}

void write_checkpoint_manifest(const std::string& path, std::uint64_t generation,
                               const std::vector<CheckpointPartRecord>& parts) {
  nlohmann::json j;
  j["format"] = "amalgam-checkpoint-parts";
  j["version"] = 1;
  j["generation"] = generation;
  j["ranks"] = parts.size();
  j["parts"] = nlohmann::json::array();
  for (std::size_t r = 0; r < parts.size(); ++r)
    j["parts"].push_back({{"rank", r},
                          {"file", parts[r].file},
                          {"particles", parts[r].particles},
                          {"bytes", parts[r].bytes},
                          {"fnv1a64", hex64(parts[r].checksum)}});
  write_file_atomic(path, j.dump(1) + "\n");
}

void remove_stale_checkpoint_parts(const std::string& dir, std::uint64_t generation) {
  std::error_code ec;
  for (const auto& e : std::filesystem::directory_iterator(dir, ec)) {
    const std::string name = e.path().filename().string();
    unsigned long long g = 0;
    int r = 0;
    if (std::sscanf(name.c_str(), "checkpoint.g%llu.r%d.amck", &g, &r) == 2 && name.size() > 5 &&
        name.compare(name.size() - 5, 5, ".amck") == 0 && g != generation)
      std::filesystem::remove(e.path(), ec);
  }
}

std::uint64_t last_checkpoint_generation(const std::string& dir) {
  std::uint64_t last = 0;
  std::error_code ec;
  for (const auto& e : std::filesystem::directory_iterator(dir, ec)) {
    unsigned long long g = 0;
    int r = 0;
    if (std::sscanf(e.path().filename().string().c_str(), "checkpoint.g%llu.r%d", &g, &r) == 2)
      last = std::max<std::uint64_t>(last, g);
  }
  return last;
}

std::unique_ptr<TempFile> stage_checkpoint(const std::string& path, Simulation& sim, int next_frame,
                                           std::uint64_t scene_fingerprint, int retries) {
  auto tmp = std::make_unique<TempFile>(path);
  FileSink sink(*tmp);
  emit_state(sink, sim.particles(), sim.time(), sim.step_count(), next_frame, retries,
             scene_fingerprint, sim.checkpoint_sections());
  return tmp;
}

void write_checkpoint(const std::string& path, Simulation& sim, int next_frame,
                      std::uint64_t scene_fingerprint, int retries) {
  stage_checkpoint(path, sim, next_frame, scene_fingerprint, retries)->commit();
}

CheckpointState read_checkpoint(const std::string& path, Simulation& sim,
                                std::uint64_t scene_fingerprint) {
  // A per-rank checkpoint's manifest: its parts joined into the single file one process writes
  // (every rank reads every part; the run's begin_run then keeps each rank's own particles).
  std::string d;
  const Simulation::Slice slice = sim.checkpoint_slice();
  std::vector<std::uint64_t> keys;
  std::uint64_t total = 0;
  const bool sliced = slice.parts > 1 && is_checkpoint_manifest(path);
  sim.before_checkpoint_read();
  if (sliced) {
    // This rank's slice of the parts (the run's `distribute` sends every particle to its owner):
    // no rank holds the whole checkpoint.
    d = join_checkpoint(path, JoinSlice{slice.part, slice.parts}, &keys, &total);
    const std::uint64_t scene = sim.set_up_particle_count();
    if (sim.variable_particle_count() ? total > sim.max_particle_count() : total != scene)
      throw InputError(path + ": checkpoint field 'particle count' is " + std::to_string(total) +
                       (sim.variable_particle_count()
                            ? ", above the " + std::to_string(sim.max_particle_count()) +
                                  " particles this scene can hold (its objects and emitters)"
                            : ", this scene has " + std::to_string(scene) + " particles"));
    sim.particles().resize(keys.size() / 2);
  } else if (is_checkpoint_manifest(path)) {
    sim.before_restore();
    d = join_checkpoint(path);
  } else {
    sim.before_restore();
    // Never more than the memory there is (a hostile size would end in bad_alloc).
    const std::uint64_t avail = available_memory_bytes();
    d = read_input_file(path, "checkpoint", avail > 0 ? avail : std::uint64_t(1) << 40);
  }
  const CheckpointState st =
      read_state(path, d, sim.particles(), scene_fingerprint, sim.restore_sections(),
                 sim.variable_particle_count() && !sliced ? sim.max_particle_count() : 0);
  try {
    if (sliced) sim.restoring_slice(std::move(keys), total);
    for (const std::string& name : st.absent) sim.fill_absent_attribute(name);
    sim.restored(st.time, st.steps);
  } catch (const InputError& e) {
    throw InputError(path + ": " + e.what());
  }
  return st;
}

}  // namespace amalgam
