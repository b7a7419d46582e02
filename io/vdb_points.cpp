// Sees OpenVDB's points headers (slow to compile): with io/surfacing.cpp, the only io files that
// do.
#include "io/vdb_points.hpp"

#include <openvdb/openvdb.h>
#include <openvdb/points/PointAttribute.h>
#include <openvdb/points/PointConversion.h>
#include <openvdb/points/PointDataGrid.h>
#include <openvdb/tools/PointIndexGrid.h>

#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cstring>
#include <fstream>
#include <cstdio>
#include <mutex>
#include <nlohmann/json.hpp>
#include <vector>

#include "core/errors.hpp"
#include "core/hash.hpp"
#include "io/files.hpp"
#include "io/vdb_file.hpp"
#include "io/writers.hpp"

namespace amalgam {

namespace {
// Appends attribute `name` with codec C and fills it from `values` (by point index).
template <class T, class C = openvdb::points::NullCodec>
void add_attribute(openvdb::points::PointDataGrid& grid,
                   const openvdb::tools::PointIndexGrid& index, const std::string& name,
                   const std::vector<T>& values) {
  using namespace openvdb::points;
  appendAttribute<T, C>(grid.tree(), name);
  populateAttribute<PointDataTree, openvdb::tools::PointIndexTree, PointAttributeVector<T>>(
      grid.tree(), index.tree(), name, PointAttributeVector<T>(values));
}

// A float attribute: half (TruncateCodec) in compact files when its range allows.
void add_floats(openvdb::points::PointDataGrid& grid, const openvdb::tools::PointIndexGrid& index,
                const PointAttribute& a, bool half) {
  if (half)
    add_attribute<float, openvdb::points::TruncateCodec>(grid, index, a.name, a.f);
  else
    add_attribute<float>(grid, index, a.name, a.f);
}

// A requested attribute (PointFields::attributes) with its OpenVDB type: float, Vec3s, Mat3s
// (TypedAttributeArray<Mat3s>, registered by openvdb::initialize) or int32.
void add_requested(openvdb::points::PointDataGrid& grid,
                   const openvdb::tools::PointIndexGrid& index, const PointAttribute& a,
                   VdbPrecision precision) {
  using T = PointAttribute::Type;
  const std::size_t n = a.type == T::Int ? a.i.size() : a.f.size() / std::size_t(a.width());
  switch (a.type) {
    case T::Float:  // von Mises stress in Pa overflows half (65504): kept float
      add_floats(grid, index, a, precision == VdbPrecision::Compact && a.name != "vonmises");
      return;
    case T::Vec3: {
      std::vector<openvdb::Vec3s> v(n);
      for (std::size_t i = 0; i < n; ++i)
        v[i] = openvdb::Vec3s(a.f[3 * i], a.f[3 * i + 1], a.f[3 * i + 2]);
      add_attribute(grid, index, a.name, v);
      return;
    }
    case T::Mat3: {
      std::vector<openvdb::math::Mat3s> m(n);
      for (std::size_t i = 0; i < n; ++i) m[i] = openvdb::math::Mat3s(&a.f[9 * i]);  // row-major
      add_attribute(grid, index, a.name, m);
      return;
    }
    case T::Int:
      add_attribute(grid, index, a.name, a.i);
      return;
  }
}

// The particle indices in ascending id order: ids 0..n-1 (every method's ids until particles are
// added or removed) placed directly, any other set sorted.
std::vector<size_t> id_order(const std::int32_t* id, size_t n) {
  std::vector<size_t> order(n, n);
  bool direct = true;
  for (size_t i = 0; i < n && direct; ++i) {
    const std::int32_t d = id[i];
    direct = d >= 0 && size_t(d) < n && order[size_t(d)] == n;
    if (direct) order[size_t(d)] = i;
  }
  if (direct) return order;
  for (size_t i = 0; i < n; ++i) order[i] = i;
  std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) { return id[a] < id[b]; });
  return order;
}

// Attribute `a` with its values in `order`.
PointAttribute reordered(const PointAttribute& a, const std::vector<size_t>& order) {
  PointAttribute r;
  r.name = a.name;
  r.type = a.type;
  const size_t w = size_t(a.width());
  if (a.type == PointAttribute::Type::Int) {
    r.i.resize(order.size());
    for (size_t k = 0; k < order.size(); ++k) r.i[k] = a.i[order[k]];
  } else {
    r.f.resize(order.size() * w);
    for (size_t k = 0; k < order.size(); ++k)
      for (size_t c = 0; c < w; ++c) r.f[k * w + c] = a.f[order[k] * w + c];
  }
  return r;
}

// OpenVDB writes a random UUID into every file's header (io::Archive::writeHeader), so two
// identical runs would write different bytes. It is replaced by one derived from the file's other
// bytes: the same content gives the same file, different content a different UUID. The header is
// magic (8 bytes), file version (4), library major and minor (4 + 4), the grid-offsets flag (1),
// then the UUID as 36 ASCII characters (8-4-4-4-12 hex digits).
constexpr std::size_t kUuidAt = 21, kUuidLen = 36;

bool looks_like_uuid(const char* u) {
  for (std::size_t i = 0; i < kUuidLen; ++i) {
    const bool dash = i == 8 || i == 13 || i == 18 || i == 23;
    const char c = u[i];
    if (dash ? c != '-' : !std::isxdigit(static_cast<unsigned char>(c))) return false;
  }
  return true;
}

void derive_uuid(const TempFile& f, const std::string& path) {
  std::vector<char> buf(std::size_t(1) << 20);
  std::uint64_t h1 = 0xcbf29ce484222325ULL, h2 = 0x84222325cbf29ce4ULL;
  off_t off = 0;
  for (;;) {
    const ssize_t r = ::pread(f.fd(), buf.data(), buf.size(), off);
    if (r < 0) throw InputError(path + ": cannot read back the VDB file written");
    if (r == 0) break;
    std::size_t n = std::size_t(r);
    char* p = buf.data();
    if (off == 0) {  // the first chunk holds the header
      if (n < kUuidAt + kUuidLen || !looks_like_uuid(p + kUuidAt))
        throw InputError(path + ": unexpected VDB header (no UUID where OpenVDB 10 writes it)");
      fnv1a64_pair(p, kUuidAt, h1, h2);
      p += kUuidAt + kUuidLen;
      n -= kUuidAt + kUuidLen;
    }
    fnv1a64_pair(p, n, h1, h2);
    off += r;
  }
  // Name-based UUID layout: version nibble 5, variant bits 10.
  unsigned char b[16];
  for (int i = 0; i < 8; ++i) b[i] = (h1 >> (8 * i)) & 0xff, b[8 + i] = (h2 >> (8 * i)) & 0xff;
  b[6] = (b[6] & 0x0f) | 0x50;
  b[8] = (b[8] & 0x3f) | 0x80;
  char uuid[kUuidLen + 1];
  std::snprintf(uuid, sizeof uuid,
                "%02x%02x%02x%02x-%02x%02x-%02x%02x-%02x%02x-%02x%02x%02x%02x%02x%02x", b[0], b[1],
                b[2], b[3], b[4], b[5], b[6], b[7], b[8], b[9], b[10], b[11], b[12], b[13], b[14],
                b[15]);
  if (::pwrite(f.fd(), uuid, kUuidLen, kUuidAt) != ssize_t(kUuidLen))
    throw InputError(path + ": cannot write the VDB file's UUID");
}

// io::File::write (OpenVDB 10, io/File.cc) opens an std::ofstream, calls Archive::write(os,
// grids, seekable = true) and closes it without looking at the stream's state: a full disk leaves a
// truncated file and no error. The same protected call, on a stream whose state is checked, writes
// the same bytes and reports the failure.
struct StreamArchive : openvdb::io::Archive {
  void write_seekable(std::ostream& os, const openvdb::GridCPtrVec& grids) const {
    Archive::write(os, grids, /*seekable=*/true);
  }
};

}  // namespace

void write_vdb_file(const std::string& path, const exec::Space& space, const char* what,
                    const std::function<openvdb::GridCPtrVec()>& build, long compression) {
  TempFile tmp(path);
  std::string error;
  exec::with_thread_limit(space, [&] {
    try {
      const openvdb::GridCPtrVec grids = build();
      errno = 0;
      StreamArchive archive;
      if (compression >= 0) archive.setCompression(std::uint32_t(compression));
      std::ofstream os(tmp.open_name(), std::ios_base::out | std::ios_base::binary);
      archive.write_seekable(os, grids);
      os.close();
      if (!os) error = std::string("write failed: ") + std::strerror(errno ? errno : EIO);
    } catch (const std::exception& e) {  // openvdb::Exception, std::bad_alloc, I/O errors
      error = std::string(e.what()).empty() ? "unknown error" : e.what();
    }
  });
  if (!error.empty()) throw InputError(path + ": cannot write " + what + ": " + error);
  derive_uuid(tmp, path);
  tmp.commit();
}

const char* vdb_precision_name(VdbPrecision p) {
  return p == VdbPrecision::Full ? "full" : "compact";
}

void write_vdb_points(const std::string& path, const PointFields& p, double voxel_size,
                      VdbPrecision precision, const exec::Space& space) {
  using namespace openvdb::points;
  static std::once_flag init;
  std::call_once(init, [] { openvdb::initialize(); });
  const bool compact = precision == VdbPrecision::Compact;
  const size_t n = p.n;
  std::vector<openvdb::Vec3R> P(n);
  std::vector<openvdb::Vec3s> v(n);
  std::vector<openvdb::Int32> id(n);
  // Points in id order: OpenVDB keeps the input order inside each voxel, so ids there ascend and
  // Blosc packs them better (jelly_drop in motion: 0.3-0.5 B per particle less than the solver's
  // cell-sorted order), and the file's order no longer depends on the solver's sorting.
  const std::vector<size_t> order = id_order(p.id, n);
  for (size_t k = 0; k < n; ++k) {
    const size_t i = order[k];
    P[k] = openvdb::Vec3R(double(p.x[i][0]), double(p.x[i][1]), double(p.x[i][2]));
    v[k] = openvdb::Vec3s(float(p.v[i][0]), float(p.v[i][1]), float(p.v[i][2]));
    id[k] = p.id[i];
  }
  const PointAttributeVector<openvdb::Vec3R> positions(P);
  const auto build = [&] {
    const openvdb::math::Transform::Ptr xform =
        openvdb::math::Transform::createLinearTransform(voxel_size);
    const auto index =
        openvdb::tools::createPointIndexGrid<openvdb::tools::PointIndexGrid>(positions, *xform);
    // P: offsets within the voxel, float (NullCodec) or 16-bit fixed point (FixedPointCodec).
    const PointDataGrid::Ptr grid =
        compact ? createPointDataGrid<FixedPointCodec<false, PositionRange>, PointDataGrid>(
                      *index, positions, *xform)
                : createPointDataGrid<NullCodec, PointDataGrid>(*index, positions, *xform);
    if (compact)
      add_attribute<openvdb::Vec3s, TruncateCodec>(*grid, *index, "v", v);
    else
      add_attribute(*grid, *index, "v", v);
    add_attribute(*grid, *index, "id", id);
    for (const PointAttribute& a : p.attributes) {
      add_requested(*grid, *index, reordered(a, order), precision);
      if (a.name == "material")  // the names by index, as a JSON array (ASCII, escaped)
        grid->insertMeta(
            "material_names",
            openvdb::StringMetadata(nlohmann::json(p.material_names).dump(-1, ' ', true)));
    }
    if (compact) compactAttributes(grid->tree());  // AttributeArray::compact on every array
    grid->setName("points");
    return openvdb::GridCPtrVec{grid};
  };
  // Compact: Blosc for the attribute arrays (TypedAttributeArray::writeBuffers) and the voxel
  // offsets, with the active-mask compression OpenVDB uses by default.
  write_vdb_file(
      path, space, "VDB points", build,
      compact ? long(openvdb::io::COMPRESS_BLOSC | openvdb::io::COMPRESS_ACTIVE_MASK) : -1L);
}

GridNodes grid_nodes(const SparseGrid& grid, double dx) {
  GridNodes g;
  g.dx = dx;
  const Real* a = grid.node4(0);
  for (const std::int32_t leaf : grid.active_leaves()) {
    const Vec3i base = grid.leaf_coords()[size_t(leaf)] * kLeafDim;
    const Real* n = a + size_t(leaf) * kLeafNodes * 4;
    for (int i = 0; i < kLeafDim; ++i)
      for (int j = 0; j < kLeafDim; ++j)
        for (int k = 0; k < kLeafDim; ++k) {
          const Real* node = n + leaf_offset(i, j, k) * 4;
          if (!(node[0] > 0)) continue;
          g.ijk.push_back({base[0] + i, base[1] + j, base[2] + k});
          g.mass.push_back(float(node[0]));
          g.velocity.push_back({float(node[1]), float(node[2]), float(node[3])});
        }
  }
  return g;
}

void write_vdb_grid_nodes(const std::string& path, const GridNodes& g, const exec::Space& space) {
  static std::once_flag init;
  std::call_once(init, [] { openvdb::initialize(); });
  write_vdb_file(path, space, "VDB grid fields", [&] {
    const openvdb::math::Transform::Ptr xform =
        openvdb::math::Transform::createLinearTransform(g.dx);
    auto mass = openvdb::FloatGrid::create(0.0f);
    auto vel = openvdb::Vec3SGrid::create(openvdb::Vec3s(0.0f));
    mass->setTransform(xform);
    vel->setTransform(xform->copy());
    mass->setName("mass");
    vel->setName("velocity");
    vel->setVectorType(openvdb::VEC_CONTRAVARIANT_RELATIVE);
    auto ma = mass->getAccessor();
    auto va = vel->getAccessor();
    for (std::size_t q = 0; q < g.mass.size(); ++q) {
      const openvdb::Coord c(g.ijk[q][0], g.ijk[q][1], g.ijk[q][2]);
      ma.setValue(c, g.mass[q]);
      va.setValue(c, openvdb::Vec3s(g.velocity[q][0], g.velocity[q][1], g.velocity[q][2]));
    }
    return openvdb::GridCPtrVec{mass, vel};
  });
}

void write_vdb_grid_fields(const std::string& path, const SparseGrid& grid, double dx,
                           const exec::Space& space) {
  write_vdb_grid_nodes(path, grid_nodes(grid, dx), space);
}

}  // namespace amalgam
