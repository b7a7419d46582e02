// Sees OpenVDB's points headers (slow to compile); see io/surfacing.hpp.
#include "io/surfacing.hpp"

#include <openvdb/openvdb.h>
#include <openvdb/points/PointConversion.h>
#include <openvdb/points/PointDataGrid.h>
#include <openvdb/points/PointRasterizeSDF.h>
#include <openvdb/tools/FastSweeping.h>
#include <openvdb/tools/Interpolation.h>
#include <openvdb/tools/LevelSetFilter.h>
#include <openvdb/tools/LevelSetUtil.h>
#include <openvdb/tools/Morphology.h>
#include <openvdb/tools/Prune.h>
#include <openvdb/tools/PointIndexGrid.h>
#include <openvdb/tools/VolumeToMesh.h>

#include <algorithm>
#include <cmath>
#include <mutex>
#include <sstream>

#include "core/errors.hpp"
#include "io/vdb_file.hpp"
#include "io/writers.hpp"

namespace amalgam {

bool parse_surfacing_method(const std::string& name, SurfacingMethod& out) {
  if (name == "smooth") return out = SurfacingMethod::Smooth, true;
  if (name == "spheres") return out = SurfacingMethod::Spheres, true;
  return false;
}

bool parse_surface_filter(const std::string& name, SurfaceFilter& out) {
  if (name == "dilate") return out = SurfaceFilter::Dilate, true;
  if (name == "smooth") return out = SurfaceFilter::Smooth, true;
  if (name == "erode") return out = SurfaceFilter::Erode, true;
  return false;
}

bool parse_surface_mesh(const std::string& name, SurfaceMeshFormat& out) {
  if (name == "none") return out = SurfaceMeshFormat::None, true;
  if (name == "obj") return out = SurfaceMeshFormat::Obj, true;
  if (name == "ply") return out = SurfaceMeshFormat::Ply, true;
  return false;
}

std::vector<SurfaceFilter> default_surface_filters(SurfacingMethod m) {
  if (m == SurfacingMethod::Spheres) return {SurfaceFilter::Dilate, SurfaceFilter::Erode};
  return {};
}

double surfacing_radius(const SurfacingSpec& s, double spacing) {
  // The sphere of the particle's lattice volume V = h^3: r = cbrt(3 V / (4 pi)).
  const double scale = s.radius_scale > 0                     ? s.radius_scale
                       : s.method == SurfacingMethod::Spheres ? 0.8
                                                              : 0.9;
  return scale * std::cbrt(3.0 / (4.0 * M_PI)) * spacing;
}

namespace {

using openvdb::FloatGrid;
using openvdb::Vec3s;
using openvdb::Vec3SGrid;
using openvdb::points::PointDataGrid;

constexpr double kHalfBand = 3.0;  // narrow band half width in voxels (LEVEL_SET_HALF_WIDTH)

// The particles to surface, flattened: world positions and velocities.
struct Particles {
  std::vector<openvdb::Vec3R> P;
  std::vector<Vec3s> v;
};

bool selected(const SurfacingSpec& s, std::int32_t material) {
  if (s.materials.empty()) return true;
  for (const std::int32_t m : s.materials)
    if (m == material) return true;
  return false;
}

Particles select(const PointFields& p, const SurfacingSpec& s) {
  Particles out;
  for (std::size_t i = 0; i < p.n; ++i) {
    if (!selected(s, p.material ? p.material[i] : 0)) continue;
    out.P.emplace_back(double(p.x[i][0]), double(p.x[i][1]), double(p.x[i][2]));
    out.v.emplace_back(float(p.v[i][0]), float(p.v[i][1]), float(p.v[i][2]));
  }
  return out;
}

// A PointDataGrid with P and v (points::createPointDataGrid, as io/vdb_points.cpp writes frames).
PointDataGrid::Ptr point_grid(const Particles& q, const openvdb::math::Transform& xform) {
  using namespace openvdb::points;
  const PointAttributeVector<openvdb::Vec3R> positions(q.P);
  const auto index =
      openvdb::tools::createPointIndexGrid<openvdb::tools::PointIndexGrid>(positions, xform);
  auto grid = createPointDataGrid<NullCodec, PointDataGrid>(*index, positions, xform);
  appendAttribute<Vec3s>(grid->tree(), "v");
  populateAttribute<PointDataTree, openvdb::tools::PointIndexTree, PointAttributeVector<Vec3s>>(
      grid->tree(), index->tree(), "v", PointAttributeVector<Vec3s>(q.v));
  return grid;
}

struct Grids {
  FloatGrid::Ptr surface;
  Vec3SGrid::Ptr v;
};

// Voids the particles enclose completely (a bubble in the water) are filled, as the scan
// conversion of tools::levelSetRebuild fills them, so the surface has no inner shells. The raw
// band can be one voxel thin, through which extractEnclosedRegion's flood would leak, so it runs on
// a copy whose band is dilated by the half width (tools::dilateActiveValues); a voxel of that copy
// with a positive value inside the enclosed region is set to -w in the field. Tunnels open to the
// outside stay.
void fill_enclosed_voids(FloatGrid& field, float w) {
  const FloatGrid::Ptr probe = field.deepCopy();
  openvdb::tools::dilateActiveValues(probe->tree(), int(kHalfBand),
                                     openvdb::tools::NN_FACE_EDGE_VERTEX,
                                     openvdb::tools::IGNORE_TILES);
  const auto enclosed = openvdb::tools::extractEnclosedRegion(*probe);
  auto inside = enclosed->getConstAccessor();
  auto out = field.getAccessor();
  const auto fill = [&](const openvdb::Coord& c) {
    if (inside.isValueOn(c)) out.setValue(c, -w);
  };
  for (auto leaf = probe->tree().cbeginLeaf(); leaf; ++leaf)  // the band and its dilation
    for (auto v = leaf->cbeginValueAll(); v; ++v)
      if (*v > 0.0f) fill(v.getCoord());
  // Positive tiles: a void wider than a leaf beyond the band. A tile is one connected region of
  // one value, so the flood leaves it whole inside the region or whole outside: a tile inside
  // becomes an inside tile (a large void costs no voxels).
  for (auto t = probe->tree().cbeginValueOff(); t; ++t) {
    if (!t.isTileValue() || *t <= 0.0f) continue;
    const openvdb::CoordBBox box = t.getBoundingBox();
    if (!inside.isValueOn(box.min())) continue;
    field.tree().fill(box, -w, false);
    out.clear();
  }
}

// The Zhu & Bridson field is an averaged-position distance (|grad| != 1, a band on one side; see
// PointRasterizeSDF.h): made a narrow-band SDF of half width w on both sides by fast sweeping
// (tools::sdfToSdf re-solves |grad phi| = 1 from the zero crossing, Zhao 2005, as FastSweeping.h
// implements it; tools::dilateSdf extends the band outwards by the half width), enclosed voids
// filled first. A first-order Eikonal solution: ~0.1-0.4 voxel from the exact distance near the
// surface, about three times cheaper than tools::levelSetRebuild's mesh-and-rescan
// (docs/benchmarks.md "Surfacing by fast sweeping").
FloatGrid::Ptr redistance(const FloatGrid& raw) {
  const float w = float(kHalfBand * raw.voxelSize()[0]);
  FloatGrid::Ptr field = raw.deepCopy();
  field->tree().voxelizeActiveTiles();
  fill_enclosed_voids(*field, w);
  FloatGrid::Ptr sdf = openvdb::tools::sdfToSdf(*field, 0.0f, 1);
  sdf = openvdb::tools::dilateSdf(*sdf, int(kHalfBand), openvdb::tools::NN_FACE_EDGE_VERTEX, 1,
                                  openvdb::tools::FastSweepingDomain::SWEEP_GREATER_THAN_ISOVALUE);
  for (auto it = sdf->tree().beginValueOn(); it; ++it)
    if (std::abs(*it) >= w) {
      it.setValue(*it > 0.0f ? w : -w);
      it.setValueOff();
    }
  openvdb::tools::changeLevelSetBackground(sdf->tree(), w);
  openvdb::tools::pruneLevelSet(sdf->tree());
  sdf->setTransform(raw.transform().copy());
  sdf->setGridClass(openvdb::GRID_LEVEL_SET);
  sdf->setName(raw.getName());
  return sdf;
}

// The level set and the closest particle's velocity on its active voxels
// (points::rasterizeSpheres / points::rasterizeSmoothSpheres with the closest-point transfer of v).
Grids rasterize(const PointDataGrid& points, double radius, const SurfacingSpec& s,
                const openvdb::math::Transform::Ptr& xform) {
  using Types = openvdb::TypeList<Vec3s>;
  const std::vector<std::string> attributes = {"v"};
  openvdb::GridPtrVec g;
  if (s.method == SurfacingMethod::Spheres)
    g = openvdb::points::rasterizeSpheres<PointDataGrid, Types>(points, radius, attributes,
                                                                kHalfBand, xform);
  else  // Zhu & Bridson: the kernel reaches twice the particle radius
    g = openvdb::points::rasterizeSmoothSpheres<PointDataGrid, Types>(points, radius, 2.0 * radius,
                                                                      attributes, kHalfBand, xform);
  Grids out;
  if (g.size() == 2) {
    out.surface = openvdb::gridPtrCast<FloatGrid>(g[0]);
    out.v = openvdb::gridPtrCast<Vec3SGrid>(g[1]);
  }
  // The averaged-position field is no distance field: made one (redistance above) so that the
  // filters, the fog ramp and the mesh see a true level set.
  if (out.surface && s.method == SurfacingMethod::Smooth && out.surface->activeVoxelCount() > 0)
    out.surface = redistance(*out.surface);
  if (!out.surface) {  // no points: an empty level set (and velocity) of the same transform
    out.surface = FloatGrid::create(float(kHalfBand * xform->voxelSize()[0]));
    out.surface->setTransform(xform);
    out.surface->setGridClass(openvdb::GRID_LEVEL_SET);
  }
  if (!out.v) {
    out.v = Vec3SGrid::create(Vec3s(0.0f));
    out.v->setTransform(xform->copy());
  }
  return out;
}

// tools::LevelSetFilter passes in the order given: dilate and erode move the surface by one
// voxel (offset -dx, +dx), smooth is one Gaussian pass of width 1.
void filter(FloatGrid& surface, const std::vector<SurfaceFilter>& filters) {
  if (filters.empty() || surface.activeVoxelCount() == 0) return;
  openvdb::tools::LevelSetFilter<FloatGrid> f(surface);
  const float dx = float(surface.voxelSize()[0]);
  for (const SurfaceFilter k : filters) {
    if (k == SurfaceFilter::Dilate) f.offset(-dx);
    if (k == SurfaceFilter::Erode) f.offset(dx);
    if (k == SurfaceFilter::Smooth) f.gaussian(1);
  }
}

// tools::volumeToMesh, quads split into two triangles, wound counter-clockwise seen from outside
// (OpenVDB's polygons face the other way); area-weighted vertex normals from the triangles, and
// the velocity grid sampled trilinearly (tools::BoxSampler) at the vertices.
SurfaceMesh mesh_of(const FloatGrid& surface, const Vec3SGrid& v, double adaptivity) {
  std::vector<Vec3s> points;
  std::vector<openvdb::Vec3I> triangles;
  std::vector<openvdb::Vec4I> quads;
  openvdb::tools::volumeToMesh(surface, points, triangles, quads, 0.0, adaptivity);
  SurfaceMesh m;
  m.triangles.reserve(triangles.size() + 2 * quads.size());
  for (const auto& t : triangles) m.triangles.push_back({t[0], t[2], t[1]});
  for (const auto& q : quads) {
    m.triangles.push_back({q[0], q[2], q[1]});
    m.triangles.push_back({q[0], q[3], q[2]});
  }
  std::vector<Vec3s> normals(points.size(), Vec3s(0.0f));
  for (const auto& t : m.triangles) {
    const Vec3s n = (points[t[1]] - points[t[0]]).cross(points[t[2]] - points[t[0]]);
    for (int k = 0; k < 3; ++k) normals[t[k]] += n;
  }
  openvdb::tools::GridSampler<Vec3SGrid, openvdb::tools::BoxSampler> sampler(v);
  m.vertices.resize(points.size());
  m.normals.resize(points.size());
  m.velocity.resize(points.size());
  for (std::size_t i = 0; i < points.size(); ++i) {
    const float len = normals[i].length();
    const Vec3s n = len > 0 ? normals[i] / len : Vec3s(0.0f);
    const Vec3s u = sampler.wsSample(openvdb::Vec3d(points[i]));
    m.vertices[i] = Vec3(Real(points[i][0]), Real(points[i][1]), Real(points[i][2]));
    m.normals[i] = Vec3(Real(n[0]), Real(n[1]), Real(n[2]));
    m.velocity[i] = Vec3(Real(u[0]), Real(u[1]), Real(u[2]));
  }
  return m;
}

// Throws InputError naming `where` when a particle cannot be surfaced: a non-finite position or
// velocity, or a position whose voxel index at `voxel` leaves OpenVDB's 32-bit coordinates (kept
// below 2^30, so that the band and the filters' dilation stay inside them too).
void check_indexable(const Particles& q, double voxel, const std::string& where) {
  const double reach = std::ldexp(1.0, 30) * voxel;
  for (std::size_t i = 0; i < q.P.size(); ++i) {
    const openvdb::Vec3R& x = q.P[i];
    const Vec3s& u = q.v[i];
    const bool x_ok = std::isfinite(x[0]) && std::isfinite(x[1]) && std::isfinite(x[2]);
    const bool v_ok = std::isfinite(u[0]) && std::isfinite(u[1]) && std::isfinite(u[2]);
    const bool near = x_ok && std::max({std::abs(x[0]), std::abs(x[1]), std::abs(x[2])}) < reach;
    if (x_ok && v_ok && near) continue;
    std::ostringstream os;  // only for the particle at fault
    os << where << ": particle " << i;
    if (!x_ok)
      os << " has a non-finite position";
    else if (!v_ok)
      os << " has a non-finite velocity";
    else
      os << " at (" << x[0] << ", " << x[1] << ", " << x[2]
         << ") m is beyond OpenVDB's coordinates at the surfacing voxel_size " << voxel
         << " m (|x| / voxel_size must stay below 2^30)";
    throw InputError(os.str());
  }
}

// Surfaces `q` and writes the files; runs every OpenVDB tool under the space's thread limit.
SurfacingStats surface_and_write(const std::string& base, const Particles& q, double spacing,
                                 const SurfacingSpec& s, const exec::Space& space) {
  if (!(s.voxel_size > 0) || !std::isfinite(s.voxel_size))
    throw InputError(base + ".vdb: surfacing voxel_size must be a positive number");
  check_indexable(q, s.voxel_size, base + ".vdb");
  SurfacingStats st;
  st.particles = q.P.size();
  const double radius = surfacing_radius(s, spacing);
  SurfaceMesh mesh;
  write_vdb_file(base + ".vdb", space, "surface VDB", [&] {
    const auto xform = openvdb::math::Transform::createLinearTransform(s.voxel_size);
    Grids g;
    {
      const PointDataGrid::Ptr points = point_grid(q, *xform);
      g = rasterize(*points, radius, s, xform);
    }
    filter(*g.surface, s.filters);
    st.active_voxels = std::size_t(g.surface->activeVoxelCount());
    if (s.mesh != SurfaceMeshFormat::None) mesh = mesh_of(*g.surface, *g.v, s.adaptivity);
    g.surface->setName("surface");
    g.v->setName("v");
    g.v->setVectorType(openvdb::VEC_CONTRAVARIANT_RELATIVE);
    openvdb::GridCPtrVec grids;
    if (s.grid_surface) grids.push_back(g.surface);
    if (s.grid_density) {
      // tools::sdfToFogVolume: 0 outside, a ramp across the inner half band, 1 inside.
      const FloatGrid::Ptr density = g.surface->deepCopy();
      openvdb::tools::sdfToFogVolume(*density);
      density->setName("density");
      density->setGridClass(openvdb::GRID_FOG_VOLUME);
      grids.push_back(density);
    }
    if (s.grid_velocity) grids.push_back(g.v);
    return grids;
  });
  st.files.push_back(base + ".vdb");
  if (s.mesh == SurfaceMeshFormat::Obj) write_mesh_obj(base + ".obj", mesh, "particle surface");
  if (s.mesh == SurfaceMeshFormat::Ply) write_mesh_ply(base + ".ply", mesh, "particle surface");
  if (s.mesh != SurfaceMeshFormat::None)
    st.files.push_back(base + (s.mesh == SurfaceMeshFormat::Obj ? ".obj" : ".ply"));
  st.vertices = mesh.vertices.size();
  st.triangles = mesh.triangles.size();
  return st;
}

void init_openvdb() {
  static std::once_flag init;
  std::call_once(init, [] { openvdb::initialize(); });
}

}  // namespace

SurfacingStats write_surfacing(const std::string& base, const PointFields& p, double spacing,
                               const SurfacingSpec& s, const exec::Space& space) {
  init_openvdb();
  return surface_and_write(base, select(p, s), spacing, s, space);
}

SurfacingStats surface_vdb_points_file(const std::string& input, const std::string& base,
                                       double spacing, const SurfacingSpec& s,
                                       const exec::Space& space) {
  init_openvdb();
  Particles q;
  double points_voxel = 0;
  std::string error;
  exec::with_thread_limit(space, [&] {
    try {
      openvdb::io::File file(input);
      file.open(false);  // no delayed loading: the file may be replaced while we read
      const auto grid = openvdb::gridPtrCast<PointDataGrid>(file.readGrid("points"));
      file.close();
      if (!grid) throw std::runtime_error("the grid \"points\" is not a point data grid");
      points_voxel = grid->voxelSize()[0];
      using openvdb::points::AttributeHandle;
      for (auto leaf = grid->tree().cbeginLeaf(); leaf; ++leaf) {
        const auto& set = leaf->attributeSet();
        for (const char* name : {"P", "v"})
          if (set.find(name) == openvdb::points::AttributeSet::INVALID_POS)
            throw std::runtime_error(std::string("the points have no attribute ") + name);
        const bool has_material =
            set.find("material") != openvdb::points::AttributeSet::INVALID_POS;
        AttributeHandle<Vec3s> P(leaf->constAttributeArray("P"));
        AttributeHandle<Vec3s> v(leaf->constAttributeArray("v"));
        std::unique_ptr<AttributeHandle<openvdb::Int32>> mat;
        if (has_material)
          mat = std::make_unique<AttributeHandle<openvdb::Int32>>(
              leaf->constAttributeArray("material"));
        for (auto it = leaf->beginIndexOn(); it; ++it) {
          if (!selected(s, mat ? mat->get(*it) : 0)) continue;
          const openvdb::Vec3d ijk = it.getCoord().asVec3d() + openvdb::Vec3d(P.get(*it));
          q.P.push_back(grid->transform().indexToWorld(ijk));
          q.v.push_back(v.get(*it));
        }
      }
    } catch (const std::exception& e) {
      error = std::string(e.what()).empty() ? "unknown error" : e.what();
    }
  });
  if (!error.empty()) throw InputError(input + ": cannot read VDB points: " + error);
  SurfacingSpec resolved = s;  // unset sizes from the points' voxel (the run's dx for MPM)
  if (!(resolved.voxel_size > 0)) resolved.voxel_size = 0.5 * points_voxel;
  if (resolved.voxel_size > 0 && std::isfinite(resolved.voxel_size))
    check_indexable(q, resolved.voxel_size, input);  // the file's fault, named as such
  return surface_and_write(base, q, spacing > 0 ? spacing : 0.5 * points_voxel, resolved, space);
}

}  // namespace amalgam
