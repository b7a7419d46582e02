#include "io/parts.hpp"

#include <algorithm>
#include <cstdio>
#include <cstring>
#include <nlohmann/json.hpp>
#include <tuple>

#include "core/errors.hpp"
#include "core/hash.hpp"
#include "io/files.hpp"
#include "io/writers.hpp"

namespace amalgam {

namespace {
constexpr char kMagic[] = "AMALGAM-POINTS\n";
constexpr std::size_t kMagicLen = sizeof(kMagic) - 1;
constexpr std::uint32_t kPartVersion = 1;
constexpr int kManifestVersion = 1;

template <class T>
void put(std::string& b, const T& v) {
  b.append(reinterpret_cast<const char*>(&v), sizeof(T));
}
template <class T>
void put_array(std::string& b, const T* p, std::size_t n) {
  if (n > 0) b.append(reinterpret_cast<const char*>(p), n * sizeof(T));
}

std::string hex(std::uint64_t v) {
  char s[20];
  std::snprintf(s, sizeof s, "%016llx", (unsigned long long)v);
  return s;
}

// A points part read back: owning arrays.
struct PointsPart {
  std::uint64_t n = 0;
  std::vector<std::uint64_t> order;
  std::vector<Vec3> x, v;
  std::vector<std::int32_t> material, id;
  std::vector<PointAttribute> attributes;
};

class Cursor {
 public:
  Cursor(const std::string& d, const std::string& path) : d_(d), path_(path) {}
  template <class T>
  void array(T* out, std::size_t n, const char* what) {
    const std::size_t bytes = n * sizeof(T);
    if (n != 0 && bytes / n != sizeof(T)) fail(what);
    if (d_.size() - 8 - pos_ < bytes) fail(what);
    if (bytes) std::memcpy(out, d_.data() + pos_, bytes);
    pos_ += bytes;
  }
  template <class T>
  T get(const char* what) {
    T v;
    array(&v, 1, what);
    return v;
  }
  bool at_end() const { return pos_ == d_.size() - 8; }
  [[noreturn]] void fail(const char* what) const {
    throw InputError(path_ + ": points part is truncated or corrupt (at " + what + ")");
  }

 private:
  const std::string& d_;
  const std::string& path_;
  std::size_t pos_ = kMagicLen;
};

PointsPart read_points_part(const std::string& path, const std::string& d) {
  if (d.size() < kMagicLen + 8 || std::memcmp(d.data(), kMagic, kMagicLen) != 0)
    throw InputError(path + ": not an Amalgam points part (bad magic)");
  std::uint64_t stored = 0;
  std::memcpy(&stored, d.data() + d.size() - 8, 8);
  if (fnv1a64(d.data(), d.size() - 8) != stored)
    throw InputError(path + ": points part is corrupt or truncated (checksum mismatch)");
  Cursor c(d, path);
  if (c.get<std::uint32_t>("version") != kPartVersion)
    throw InputError(path + ": points part format version is not " + std::to_string(kPartVersion));
  if (c.get<std::uint32_t>("precision") != sizeof(Real))
    throw InputError(path + ": points part was written by a build of another precision");
  PointsPart p;
  p.n = c.get<std::uint64_t>("count");
  if (p.n > d.size()) c.fail("count");  // every point takes more than a byte
  const std::size_t n = std::size_t(p.n);
  p.order.resize(2 * n);
  c.array(p.order.data(), 2 * n, "order");
  p.x.resize(n);
  p.v.resize(n);
  c.array(reinterpret_cast<Real*>(p.x.data()), 3 * n, "x");
  c.array(reinterpret_cast<Real*>(p.v.data()), 3 * n, "v");
  p.material.resize(n);
  p.id.resize(n);
  c.array(p.material.data(), n, "material");
  c.array(p.id.data(), n, "id");
  const auto na = c.get<std::uint32_t>("attribute count");
  if (na > 64) c.fail("attribute count");
  for (std::uint32_t k = 0; k < na; ++k) {
    const auto len = c.get<std::uint32_t>("attribute name length");
    if (len > 256) c.fail("attribute name length");
    PointAttribute a;
    a.name.resize(len);
    c.array(a.name.data(), len, "attribute name");
    const auto type = c.get<std::uint32_t>("attribute type");
    if (type > std::uint32_t(PointAttribute::Type::Int)) c.fail("attribute type");
    a.type = PointAttribute::Type(type);
    if (c.get<std::uint32_t>("attribute width") != std::uint32_t(a.width()))
      c.fail("attribute width");
    if (a.type == PointAttribute::Type::Int) {
      a.i.resize(n);
      c.array(a.i.data(), n, "attribute values");
    } else {
      a.f.resize(n * std::size_t(a.width()));
      c.array(a.f.data(), a.f.size(), "attribute values");
    }
    p.attributes.push_back(std::move(a));
  }
  if (!c.at_end()) c.fail("end (trailing bytes)");
  return p;
}

VdbPrecision precision_of(const std::string& s, const std::string& path) {
  if (s == vdb_precision_name(VdbPrecision::Full)) return VdbPrecision::Full;
  if (s == vdb_precision_name(VdbPrecision::Compact)) return VdbPrecision::Compact;
  throw InputError(path + ": /vdb_precision: unknown value '" + s + "'");
}
}  // namespace

PartFile part_file_record(const std::string& dir, const std::string& name) {
  const std::string d = read_input_file(dir + "/" + name, "part", std::uint64_t(1) << 40);
  return {name, d.size(), fnv1a64(d.data(), d.size())};
}

void write_points_part(const std::string& path, const PointFields& p,
                       const std::vector<std::uint64_t>& order) {
  std::string b;
  b.reserve(64 + p.n * (16 + 6 * sizeof(Real) + 8));
  b.append(kMagic, kMagicLen);
  put(b, kPartVersion);
  put(b, std::uint32_t(sizeof(Real)));
  put(b, std::uint64_t(p.n));
  put_array(b, order.data(), 2 * p.n);
  put_array(b, reinterpret_cast<const Real*>(p.x), 3 * p.n);
  put_array(b, reinterpret_cast<const Real*>(p.v), 3 * p.n);
  put_array(b, p.material, p.n);
  put_array(b, p.id, p.n);
  put(b, std::uint32_t(p.attributes.size()));
  for (const PointAttribute& a : p.attributes) {
    put(b, std::uint32_t(a.name.size()));
    b.append(a.name);
    put(b, std::uint32_t(a.type));
    put(b, std::uint32_t(a.width()));
    if (a.type == PointAttribute::Type::Int)
      put_array(b, a.i.data(), p.n);
    else
      put_array(b, a.f.data(), p.n * std::size_t(a.width()));
  }
  put(b, fnv1a64(b.data(), b.size()));
  write_file_atomic(path, b);
}

std::string frame_manifest_name(int frame) {
  char s[64];
  std::snprintf(s, sizeof s, "frame_%04d.manifest.json", frame);
  return s;
}

void write_frame_manifest(const std::string& dir, const FrameManifest& m) {
  nlohmann::json j;
  j["format"] = "amalgam-frame-parts";
  j["version"] = kManifestVersion;
  j["frame"] = m.frame;
  j["time"] = m.time;
  j["ranks"] = m.ranks;
  j["voxel_size"] = m.voxel_size;
  j["vdb_precision"] = vdb_precision_name(m.vdb_precision);
  j["formats"] = nlohmann::json::array();
  if (m.ply) j["formats"].push_back("ply");
  if (m.vdb) j["formats"].push_back("vdb");
  j["material_names"] = m.material_names;
  j["parts"] = nlohmann::json::array();
  std::uint64_t total = 0;
  for (int r = 0; r < m.ranks; ++r) {
    nlohmann::json part;
    part["rank"] = r;
    part["particles"] = m.particles[std::size_t(r)];
    total += m.particles[std::size_t(r)];
    part["files"] = nlohmann::json::array();
    for (const PartFile& f : m.files[std::size_t(r)])
      part["files"].push_back({{"file", f.file}, {"bytes", f.bytes}, {"fnv1a64", hex(f.checksum)}});
    j["parts"].push_back(part);
  }
  j["particles"] = total;
  write_file_atomic(dir + "/" + frame_manifest_name(m.frame), j.dump(1) + "\n");
}

FrameManifest read_frame_manifest(const std::string& path) {
  const std::string text = read_input_file(path, "frame manifest", std::uint64_t(1) << 26);
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(text);
  } catch (const nlohmann::json::exception& e) {
    throw InputError(path + ": frame manifest is not valid JSON: " + e.what());
  }
  std::string key;
  try {
    FrameManifest m;
    auto at = [&](const nlohmann::json& o, const char* k, const std::string& where) {
      key = where + "/" + k;
      return o.at(k);
    };
    if (at(j, "format", "").get<std::string>() != "amalgam-frame-parts" ||
        at(j, "version", "").get<int>() != kManifestVersion)
      throw InputError(path + ": " + key + ": not an Amalgam frame manifest of version " +
                       std::to_string(kManifestVersion));
    m.frame = at(j, "frame", "").get<int>();
    m.time = at(j, "time", "").get<double>();
    m.ranks = at(j, "ranks", "").get<int>();
    m.voxel_size = at(j, "voxel_size", "").get<double>();
    m.vdb_precision = precision_of(at(j, "vdb_precision", "").get<std::string>(), path);
    for (const std::string& f : at(j, "formats", "").get<std::vector<std::string>>()) {
      m.ply = m.ply || f == "ply";
      m.vdb = m.vdb || f == "vdb";
    }
    m.material_names = at(j, "material_names", "").get<std::vector<std::string>>();
    const nlohmann::json& parts = at(j, "parts", "");
    if (m.ranks < 1 || m.ranks > 1 << 20 || !parts.is_array() ||
        parts.size() != std::size_t(m.ranks))
      throw InputError(path + ": /parts: expected one part per rank (" + std::to_string(m.ranks) +
                       ")");
    for (int r = 0; r < m.ranks; ++r) {
      const std::string w = "/parts/" + std::to_string(r);
      const nlohmann::json& p = parts[std::size_t(r)];
      if (at(p, "rank", w).get<int>() != r)
        throw InputError(path + ": " + key + ": expected " + std::to_string(r));
      m.particles.push_back(at(p, "particles", w).get<std::uint64_t>());
      std::vector<PartFile> files;
      std::size_t k = 0;
      for (const nlohmann::json& f : at(p, "files", w)) {
        const std::string fw = w + "/files/" + std::to_string(k++);
        PartFile pf;
        pf.file = at(f, "file", fw).get<std::string>();
        if (pf.file.empty() || pf.file.find('/') != std::string::npos || pf.file[0] == '.')
          throw InputError(path + ": " + key + ": '" + pf.file +
                           "' is not a file name in the run directory");
        pf.bytes = at(f, "bytes", fw).get<std::uint64_t>();
        const std::string c = at(f, "fnv1a64", fw).get<std::string>();
        char* end = nullptr;
        pf.checksum = std::strtoull(c.c_str(), &end, 16);
        if (c.size() != 16 || *end)
          throw InputError(path + ": " + key + ": not a 64-bit hex value");
        files.push_back(pf);
      }
      m.files.push_back(std::move(files));
    }
    return m;
  } catch (const nlohmann::json::exception& e) {
    throw InputError(path + ": " + key + ": missing or of the wrong type (" + e.what() + ")");
  }
}

std::string encode_part_files(std::uint64_t particles, const std::vector<PartFile>& files) {
  nlohmann::json j;
  j["particles"] = particles;
  j["files"] = nlohmann::json::array();
  for (const PartFile& f : files)
    j["files"].push_back({{"file", f.file}, {"bytes", f.bytes}, {"checksum", f.checksum}});
  return j.dump();
}

void decode_part_files(const std::string& bytes, std::uint64_t& particles,
                       std::vector<PartFile>& files) {
  const nlohmann::json j = nlohmann::json::parse(bytes);
  particles = j.at("particles").get<std::uint64_t>();
  files.clear();
  for (const nlohmann::json& f : j.at("files"))
    files.push_back({f.at("file").get<std::string>(), f.at("bytes").get<std::uint64_t>(),
                     f.at("checksum").get<std::uint64_t>()});
}

std::vector<std::string> merge_frame(const std::string& dir, const FrameManifest& m,
                                     const exec::Space& space) {
  const std::string manifest = dir + "/" + frame_manifest_name(m.frame);
  std::vector<PointsPart> parts;
  for (int r = 0; r < m.ranks; ++r) {
    const PartFile* pts = nullptr;
    for (const PartFile& f : m.files[std::size_t(r)])
      if (f.file.size() > 4 && f.file.compare(f.file.size() - 4, 4, ".pts") == 0) pts = &f;
    if (!pts)
      throw InputError(manifest + ": the part of rank " + std::to_string(r) +
                       " lists no .pts file");
    const std::string path = dir + "/" + pts->file;
    const std::string what = " (part of rank " + std::to_string(r) + ")";
    std::string d;
    try {
      d = read_input_file(path, "points part", std::uint64_t(1) << 40);
    } catch (const InputError& e) {
      throw InputError(e.what() + what);
    }
    if (d.size() != pts->bytes || fnv1a64(d.data(), d.size()) != pts->checksum)
      throw InputError(path + what + ": does not match the manifest " + manifest +
                       " (size or checksum)");
    try {
      parts.push_back(read_points_part(path, d));
    } catch (const InputError& e) {
      throw InputError(e.what() + what);
    }
    if (parts.back().n != m.particles[std::size_t(r)])
      throw InputError(path + what + ": holds " + std::to_string(parts.back().n) +
                       " points, the manifest says " + std::to_string(m.particles[std::size_t(r)]));
    const PointsPart& first = parts.front();
    bool same = parts.back().attributes.size() == first.attributes.size();
    for (std::size_t a = 0; same && a < first.attributes.size(); ++a)
      same = parts.back().attributes[a].name == first.attributes[a].name &&
             parts.back().attributes[a].type == first.attributes[a].type;
    if (!same) throw InputError(path + what + ": its attributes differ from rank 0's");
  }
  // The single process's order: every point by its keys.
  std::vector<std::tuple<std::uint64_t, std::uint64_t, std::uint32_t, std::uint32_t>> all;
  for (std::size_t r = 0; r < parts.size(); ++r)
    for (std::uint64_t i = 0; i < parts[r].n; ++i)
      all.emplace_back(parts[r].order[2 * i], parts[r].order[2 * i + 1], std::uint32_t(r),
                       std::uint32_t(i));
  std::sort(all.begin(), all.end());
  const std::size_t n = all.size();
  std::vector<Vec3> x(n), v(n);
  std::vector<std::int32_t> material(n), id(n);
  PointFields p;
  p.n = n;
  p.material_names = m.material_names;
  for (const PointAttribute& a : parts.front().attributes) {
    PointAttribute out{a.name, a.type, {}, {}};
    if (a.type == PointAttribute::Type::Int)
      out.i.resize(n);
    else
      out.f.resize(n * std::size_t(a.width()));
    p.attributes.push_back(std::move(out));
  }
  for (std::size_t k = 0; k < n; ++k) {
    const PointsPart& src = parts[std::get<2>(all[k])];
    const std::size_t i = std::get<3>(all[k]);
    x[k] = src.x[i], v[k] = src.v[i], material[k] = src.material[i], id[k] = src.id[i];
    for (std::size_t a = 0; a < p.attributes.size(); ++a) {
      PointAttribute& o = p.attributes[a];
      const PointAttribute& s = src.attributes[a];
      const std::size_t w = std::size_t(o.width());
      if (o.type == PointAttribute::Type::Int)
        o.i[k] = s.i[i];
      else
        std::copy(s.f.begin() + std::ptrdiff_t(w * i), s.f.begin() + std::ptrdiff_t(w * i + w),
                  o.f.begin() + std::ptrdiff_t(w * k));
    }
  }
  p.x = x.data(), p.v = v.data(), p.material = material.data(), p.id = id.data();
  char base[64];
  std::snprintf(base, sizeof base, "/frame_%04d.", m.frame);
  std::vector<std::string> written;
  if (m.ply) {
    written.push_back(dir + base + "ply");
    write_ply_points(written.back(), p);
  }
  if (m.vdb) {
    written.push_back(dir + base + "vdb");
    write_vdb_points(written.back(), p, m.voxel_size, m.vdb_precision, space);
  }
  return written;
}

}  // namespace amalgam
