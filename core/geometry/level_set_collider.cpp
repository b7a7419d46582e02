// Collider fields over OpenVDB trees (level_set_collider.hpp). Values are written only by
// prepare() (serially between kernels; a block's voxels computed in parallel through exec, each
// a pure function of the mesh and its index); kernels read the trees through non-registering
// ValueAccessors constructed per sample, so no tree is mutated or shared mutably in a loop.
#include "core/geometry/level_set_collider.hpp"

#include <openvdb/io/File.h>
#include <openvdb/math/Proximity.h>
#include <openvdb/openvdb.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <limits>
#include <map>
#include <type_traits>
#include <mutex>
#include <unordered_map>

#include "core/errors.hpp"
#include "core/exec/exec.hpp"

namespace amalgam {

namespace {

using openvdb::Coord;
using FloatLeaf = openvdb::FloatTree::LeafNodeType;
using VecLeaf = openvdb::Vec3STree::LeafNodeType;

void init_vdb() {
  static std::once_flag once;
  std::call_once(once, [] { openvdb::initialize(); });
}

double to_d(float v) {
  return double(v);
}
Vec3d to_d(const openvdb::Vec3s& v) {
  return Vec3d(v[0], v[1], v[2]);
}

// Trilinear value of a tree at index-space point g (voxel centres at integers) through a
// non-registering accessor (thread-safe on a const tree). The gradient per index unit, if asked,
// is the trilinear interpolation of the 8 voxels' central differences (OpenVDB's
// math::ISGradient<CD_2ND>): symmetric, so the normal on top of a sphere points straight up (the
// interpolant's own one-sided gradient tilts it by up to a voxel's slope).
template <class TreeT, class V>
V sample_tree(const TreeT& tree, const Vec3d& g, Vec3d* grad_index) {
  // A point beyond 2^30 voxels or not finite (a particle that blew up in the pass that moved it,
  // before the stability check reports it) reads the background: no out-of-range float-to-int
  // conversion (undefined behaviour).
  constexpr double kFar = double(1 << 30);
  if (!(std::abs(g[0]) < kFar && std::abs(g[1]) < kFar && std::abs(g[2]) < kFar)) {
    if (grad_index) grad_index->setZero();
    return to_d(tree.background());
  }
  openvdb::tree::ValueAccessor<const TreeT, false> acc(tree);
  const Vec3d fl(std::floor(g[0]), std::floor(g[1]), std::floor(g[2]));
  const Coord c0{int(fl[0]), int(fl[1]), int(fl[2])};
  V c[2][2][2];
  for (int a = 0; a < 2; ++a)
    for (int b = 0; b < 2; ++b)
      for (int d = 0; d < 2; ++d) c[a][b][d] = to_d(acc.getValue(c0.offsetBy(a, b, d)));
  if constexpr (std::is_arithmetic_v<V>) {
    if (grad_index) {
      Vec3d cd[2][2][2];
      for (int a = 0; a < 2; ++a)
        for (int b = 0; b < 2; ++b)
          for (int d = 0; d < 2; ++d) {
            const Coord q = c0.offsetBy(a, b, d);
            auto at = [&](int x, int y, int z) {
              return double(acc.getValue(q.offsetBy(x, y, z)));
            };
            cd[a][b][d] = 0.5 * Vec3d(at(1, 0, 0) - at(-1, 0, 0), at(0, 1, 0) - at(0, -1, 0),
                                      at(0, 0, 1) - at(0, 0, -1));
          }
      *grad_index = trilinear(cd, Vec3d(g - fl));
    }
  }
  return trilinear(c, Vec3d(g - fl));
}

// One frame of a collider: phi (world gradient) and, if it has one, a velocity field.
class LevelSetFrame {
 public:
  virtual ~LevelSetFrame() = default;
  virtual double sample(const Vec3d& p, Vec3d* grad, Vec3d* vel) const = 0;
  virtual bool has_velocity() const = 0;
  virtual void build(const std::vector<Box3>&, const exec::Space&) {}
  virtual std::size_t voxels() const = 0;
  virtual std::size_t bytes() const = 0;
};

// A triangle mesh sampled lazily into blocks (OpenVDB leaves of 8^3 voxels of size h, voxel
// centres at h * ijk). A built voxel holds the exact signed distance within kLevelSetBand voxels
// of the surface and +-band beyond it.
//
// Sign: within the band, from the nearest triangle by the angle-weighted pseudo-normal of the
// nearest feature (face, edge or vertex; Baerentzen & Aanaes 2005, exact for a closed mesh, and
// the side of the nearest face for an open sheet such as a ground plane). Beyond the band, the
// surface never passes between two neighbouring voxels (both are more than band - h from it), so
// a block's far voxels take the sign of their neighbours by flood fill from the band; a block with
// no voxel in the band lies wholly on one side, whose sign is that of the mesh's nearest
// triangle to its centre (an O(triangles) test per such block). So a point deep inside a closed
// mesh is negative wherever it is built, with no narrow band over the whole mesh (what makes a
// 100 m ground cost what the material touches; tools::meshToVolume voxelises the whole surface).
// Every voxel is a pure function of the mesh and its index: the built set never changes values.
class MeshLevelSet final : public LevelSetFrame {
 public:
  MeshLevelSet(std::shared_ptr<const TriangleMesh> mesh, std::vector<Vec3d> vertex_velocity,
               double h)
      : mesh_(std::move(mesh)), vv_(std::move(vertex_velocity)), h_(h), band_(kLevelSetBand * h) {
    init_vdb();
    const auto& V = mesh_->vertices;
    pts_.reserve(V.size());
    for (const auto& v : V) pts_.emplace_back(v[0], v[1], v[2]);
    const auto& T = mesh_->triangles;
    face_n_.resize(T.size());
    edge_n_.resize(T.size());
    vert_n_.assign(V.size(), Vec3d::Zero());
    std::unordered_map<std::uint64_t, Vec3d> edge_sum;
    for (std::size_t t = 0; t < T.size(); ++t) {
      const Vec3d &a = V[size_t(T[t][0])], &b = V[size_t(T[t][1])], &c = V[size_t(T[t][2])];
      const Vec3d n = (b - a).cross(c - a);
      face_n_[t] = n.norm() > 0 ? Vec3d(n.normalized()) : Vec3d::Zero();
      if (n.norm() > 0) live_.push_back(int(t));
      Box3 box{a.cwiseMin(b).cwiseMin(c), a.cwiseMax(b).cwiseMax(c)};
      tri_box_.push_back(box);
      for (int e = 0; e < 3; ++e) {
        const auto i = size_t(T[t][size_t(e)]);
        const Vec3d u = V[size_t(T[t][size_t((e + 1) % 3)])] - V[i];
        const Vec3d w = V[size_t(T[t][size_t((e + 2) % 3)])] - V[i];
        const double nu = u.norm(), nw = w.norm();
        if (nu > 0 && nw > 0)  // angle at the vertex weights the face normal
          vert_n_[i] += std::acos(std::clamp(u.dot(w) / (nu * nw), -1.0, 1.0)) * face_n_[t];
        // (an Eigen vector's default constructor leaves it uninitialised: start at zero)
        edge_sum.emplace(edge_key(t, e), Vec3d::Zero()).first->second += face_n_[t];
      }
    }
    for (std::size_t t = 0; t < T.size(); ++t)
      for (int e = 0; e < 3; ++e) edge_n_[t][size_t(e)] = edge_sum[edge_key(t, e)];
    phi_ = std::make_shared<openvdb::FloatTree>(float(band_));
    if (!vv_.empty()) vel_ = std::make_shared<openvdb::Vec3STree>(openvdb::Vec3s(0.0f));
  }

  bool has_velocity() const override { return bool(vel_); }

  double sample(const Vec3d& p, Vec3d* grad, Vec3d* vel) const override {
    const Vec3d g = p / h_;
    Vec3d gi;
    const double v = sample_tree<openvdb::FloatTree, double>(*phi_, g, grad ? &gi : nullptr);
    if (grad) *grad = gi / h_;
    if (vel)
      *vel = vel_ ? sample_tree<openvdb::Vec3STree, Vec3d>(*vel_, g, nullptr) : Vec3d::Zero();
    return v;
  }

  void build(const std::vector<Box3>& boxes, const exec::Space& space) override {
    std::vector<Coord> need;
    for (const Box3& b : boxes) {  // the voxels a trilinear sample in the box reads, by block
      Coord lo, hi;
      for (int a = 0; a < 3; ++a) {
        lo[a] = int(std::floor(std::floor(b.lo[a] / h_) / 8.0)) * 8;
        hi[a] = int(std::floor((std::floor(b.hi[a] / h_) + 1) / 8.0)) * 8;
      }
      for (int i = lo[0]; i <= hi[0]; i += 8)
        for (int j = lo[1]; j <= hi[1]; j += 8)
          for (int k = lo[2]; k <= hi[2]; k += 8)
            if (!phi_->probeConstLeaf(Coord(i, j, k))) need.emplace_back(i, j, k);
    }
    std::sort(need.begin(), need.end());
    need.erase(std::unique(need.begin(), need.end()), need.end());
    if (need.empty()) return;
    std::vector<FloatLeaf*> leaves(need.size(), nullptr);
    std::vector<VecLeaf*> vleaves(need.size(), nullptr);
    exec::parallel_for(
        space, "collider.mesh_blocks", exec::Index(need.size()),
        [&](exec::Index i) { fill_block(need[size_t(i)], leaves[size_t(i)], vleaves[size_t(i)]); },
        1);
    for (std::size_t i = 0; i < need.size(); ++i) {  // the trees change only here, serially
      phi_->addLeaf(leaves[i]);
      if (vel_) vel_->addLeaf(vleaves[i]);
    }
  }

  std::size_t voxels() const override { return phi_->leafCount() * FloatLeaf::SIZE; }
  std::size_t bytes() const override {
    return std::size_t(phi_->memUsage()) + (vel_ ? std::size_t(vel_->memUsage()) : 0);
  }

 private:
  struct Nearest {
    double d2 = std::numeric_limits<double>::infinity();
    int tri = -1;
    openvdb::Vec3d cp, uvw;
  };

  std::uint64_t edge_key(std::size_t t, int e) const {
    std::uint64_t a = std::uint32_t(mesh_->triangles[t][size_t(e)]);
    std::uint64_t b = std::uint32_t(mesh_->triangles[t][size_t((e + 1) % 3)]);
    if (a > b) std::swap(a, b);
    return (a << 32) | b;
  }

  template <class Range>
  Nearest nearest(const openvdb::Vec3d& p, const Range& tris) const {
    Nearest best;
    for (const int t : tris) {
      const auto& tri = mesh_->triangles[size_t(t)];
      openvdb::Vec3d uvw;
      const openvdb::Vec3d cp = openvdb::math::closestPointOnTriangleToPoint(
          pts_[size_t(tri[0])], pts_[size_t(tri[1])], pts_[size_t(tri[2])], p, uvw);
      const double d2 = (p - cp).lengthSqr();
      if (d2 < best.d2) best = Nearest{d2, t, cp, uvw};
    }
    return best;
  }

  // -1 inside, +1 outside: the side of the nearest feature's pseudo-normal.
  double side(const openvdb::Vec3d& p, const Nearest& n) const {
    const auto& tri = mesh_->triangles[size_t(n.tri)];
    const int zeros = (n.uvw[0] == 0) + (n.uvw[1] == 0) + (n.uvw[2] == 0);
    Vec3d pn;
    if (zeros >= 2) {  // a vertex
      const int v = n.uvw[0] != 0 ? 0 : n.uvw[1] != 0 ? 1 : 2;
      pn = vert_n_[size_t(tri[size_t(v)])];
    } else if (zeros == 1) {  // the edge opposite the zero weight
      const int z = n.uvw[0] == 0 ? 0 : n.uvw[1] == 0 ? 1 : 2;
      pn = edge_n_[size_t(n.tri)][size_t((z + 1) % 3)];
    } else {
      pn = face_n_[size_t(n.tri)];
    }
    const openvdb::Vec3d d = p - n.cp;
    return Vec3d(d[0], d[1], d[2]).dot(pn) < 0 ? -1.0 : 1.0;
  }

  void fill_block(const Coord& origin, FloatLeaf*& leaf, VecLeaf*& vleaf) const {
    const double band = band_;
    const Vec3d lo = h_ * Vec3d(origin[0], origin[1], origin[2]) - Vec3d::Constant(band);
    const Vec3d hi = lo + Vec3d::Constant(7 * h_ + 2 * band);
    std::vector<int> cand;
    for (const int t : live_) {
      const Box3& b = tri_box_[size_t(t)];
      if ((b.lo.array() <= hi.array()).all() && (b.hi.array() >= lo.array()).all())
        cand.push_back(t);
    }
    float phi[512];
    openvdb::Vec3s vel[512];
    signed char sign[512];  // 0: not known yet
    int known = 0;
    for (int i = 0; i < 8; ++i)
      for (int j = 0; j < 8; ++j)
        for (int k = 0; k < 8; ++k) {
          const int o = (i << 6) | (j << 3) | k;  // FloatLeaf::coordToOffset
          const openvdb::Vec3d p = h_ * openvdb::Vec3d(origin[0] + i, origin[1] + j, origin[2] + k);
          const Nearest n = nearest(p, cand);
          vel[o] = openvdb::Vec3s(0.0f);
          sign[o] = 0;
          if (n.tri < 0 || n.d2 > band * band) continue;
          const double s = side(p, n);
          sign[o] = s < 0 ? -1 : 1;
          phi[o] = float(s * std::sqrt(n.d2));
          ++known;
          if (!vv_.empty()) {
            const auto& tri = mesh_->triangles[size_t(n.tri)];
            Vec3d v = Vec3d::Zero();
            for (int a = 0; a < 3; ++a) v += n.uvw[a] * vv_[size_t(tri[size_t(a)])];
            vel[o] = openvdb::Vec3s(float(v[0]), float(v[1]), float(v[2]));
          }
        }
    if (known == 0) {  // wholly on one side: the side of the mesh's nearest triangle
      const openvdb::Vec3d c =
          h_ * openvdb::Vec3d(origin[0] + 3.5, origin[1] + 3.5, origin[2] + 3.5);
      const Nearest n = nearest(c, live_);
      const signed char s = n.tri < 0 || side(c, n) > 0 ? 1 : -1;
      for (int o = 0; o < 512; ++o) sign[o] = s, phi[o] = float(s * band);
    } else {
      for (bool changed = true; changed;) {  // flood fill of the far voxels' sign, in index order
        changed = false;
        for (int o = 0; o < 512; ++o) {
          if (sign[o]) continue;
          const int i = o >> 6, j = (o >> 3) & 7, k = o & 7;
          const int nb[6] = {i > 0 ? o - 64 : -1, i < 7 ? o + 64 : -1, j > 0 ? o - 8 : -1,
                             j < 7 ? o + 8 : -1,  k > 0 ? o - 1 : -1,  k < 7 ? o + 1 : -1};
          for (const int q : nb)
            if (q >= 0 && sign[q]) {
              sign[o] = sign[q];
              phi[o] = float(sign[q] * band);
              changed = true;
              break;
            }
        }
      }
    }
    leaf = new FloatLeaf(origin, float(band), true);
    for (int o = 0; o < 512; ++o) leaf->setValueOnly(openvdb::Index(o), phi[o]);
    if (vel_) {
      vleaf = new VecLeaf(origin, openvdb::Vec3s(0.0f), true);
      for (int o = 0; o < 512; ++o) vleaf->setValueOnly(openvdb::Index(o), vel[o]);
    }
  }

  std::shared_ptr<const TriangleMesh> mesh_;
  std::vector<Vec3d> vv_;  // vertex velocities (a sequence frame), or empty
  double h_, band_;
  std::vector<openvdb::Vec3d> pts_;
  std::vector<Vec3d> face_n_, vert_n_;
  std::vector<std::array<Vec3d, 3>> edge_n_;  // per triangle edge (e, e+1): sum of face normals
  std::vector<Box3> tri_box_;
  std::vector<int> live_;  // triangles of non-zero area
  std::shared_ptr<openvdb::FloatTree> phi_;
  std::shared_ptr<openvdb::Vec3STree> vel_;
};

// Reads the float level-set grid `name` (empty: the first) and the velocity grid `v` of a .vdb.
// Every OpenVDB exception (a corrupt or hostile file) becomes an InputError naming the file.
struct VdbGrids {
  openvdb::FloatGrid::Ptr phi;
  openvdb::Vec3SGrid::Ptr v;
};
openvdb::GridBase::Ptr find_level_set(const openvdb::GridPtrVec& grids, const std::string& name) {
  for (const auto& g : grids)
    if ((name.empty() || g->getName() == name) && g->isType<openvdb::FloatGrid>() &&
        g->getGridClass() == openvdb::GRID_LEVEL_SET)
      return g;
  return nullptr;
}
std::string describe_missing(const openvdb::GridPtrVec& grids, const std::string& name) {
  std::string have;
  for (const auto& g : grids)
    have += (have.empty() ? "" : ", ") +
            ("\"" + g->getName() + "\" (" + g->type() + ", " +
             openvdb::GridBase::gridClassToString(g->getGridClass()) + ")");
  return (name.empty() ? std::string("holds no float level-set grid")
                       : "holds no float level-set grid named \"" + name + "\"") +
         " (grids: " + (have.empty() ? "none" : have) + ")";
}

VdbGrids read_vdb(const std::string& path, const std::string& name) {
  init_vdb();
  VdbGrids out;
  try {
    openvdb::io::File file(path);
    file.open(false);
    const auto meta = file.readAllGridMetadata();
    const auto g = find_level_set(*meta, name);
    if (!g) throw InputError(path + ": " + describe_missing(*meta, name));
    out.phi = openvdb::gridPtrCast<openvdb::FloatGrid>(file.readGrid(g->getName()));
    for (const auto& m : *meta)
      if (m->getName() == "v" && m->isType<openvdb::Vec3SGrid>())
        out.v = openvdb::gridPtrCast<openvdb::Vec3SGrid>(file.readGrid("v"));
    file.close();
  } catch (const openvdb::Exception& e) {
    throw InputError(path + ": cannot read the level set: " + e.what());
  } catch (const std::bad_alloc&) {
    throw InputError(path + ": cannot read the level set: out of memory (corrupt file?)");
  }
  if (!out.phi || !out.phi->transform().isLinear())
    throw InputError(path + ": the level set's transform is not linear");
  return out;
}

class VdbFrame final : public LevelSetFrame {
 public:
  explicit VdbFrame(VdbGrids g) : g_(std::move(g)) {}
  bool has_velocity() const override { return bool(g_.v); }
  double sample(const Vec3d& p, Vec3d* grad, Vec3d* vel) const override {
    const openvdb::Vec3d w(p[0], p[1], p[2]);
    const auto& xf = g_.phi->transform();
    const openvdb::Vec3d ip = xf.worldToIndex(w);
    Vec3d gi;
    const double v = sample_tree<openvdb::FloatTree, double>(
        g_.phi->tree(), Vec3d(ip[0], ip[1], ip[2]), grad ? &gi : nullptr);
    if (grad) {  // d phi / d world = J^-T d phi / d index
      const openvdb::Vec3d gw = xf.baseMap()->applyIJT(openvdb::Vec3d(gi[0], gi[1], gi[2]), ip);
      *grad = Vec3d(gw[0], gw[1], gw[2]);
    }
    if (vel) {
      *vel = Vec3d::Zero();
      if (g_.v) {
        const openvdb::Vec3d iv = g_.v->transform().worldToIndex(w);
        *vel = sample_tree<openvdb::Vec3STree, Vec3d>(g_.v->tree(), Vec3d(iv[0], iv[1], iv[2]),
                                                      nullptr);
      }
    }
    return v;
  }
  std::size_t voxels() const override { return std::size_t(g_.phi->activeVoxelCount()); }
  std::size_t bytes() const override {
    return std::size_t(g_.phi->memUsage()) + (g_.v ? std::size_t(g_.v->memUsage()) : 0);
  }

 private:
  VdbGrids g_;
};

// Frames 0 .. count-1 at times k / rate, phi linear in time between the two frames bracketing t
// (held constant beyond the last). Only those two are kept (loaded by prepare, in order).
class FramedField final : public ColliderField {
 public:
  using Loader = std::function<std::shared_ptr<LevelSetFrame>(int)>;
  FramedField(int count, double rate, Loader load)
      : count_(count), rate_(rate), load_(std::move(load)) {}

  bool deforming() const override { return count_ > 1; }

  void prepare(const std::vector<Box3>& boxes, Real t, const exec::Space& space) override {
    int a, b;
    double u;
    bracket(t, a, b, u);
    exec::with_thread_limit(space, [&] {  // OpenVDB reads and frees trees with TBB
      for (auto it = loaded_.begin(); it != loaded_.end();)
        it = (it->first == a || it->first == b) ? std::next(it) : loaded_.erase(it);
      for (const int k : {a, b})
        if (!loaded_.count(k)) loaded_[k] = load_(k);
    });
    fa_ = loaded_[a].get(), fb_ = loaded_[b].get(), a_ = a;
    loaded_[a]->build(boxes, space);  // blocks computed through exec::parallel_for
    if (b != a) loaded_[b]->build(boxes, space);
  }

  Real sample(const Vec3& p, Real t, Vec3* grad, Vec3* vel) const override {
    if (!fa_) return Real(kLevelSetBand);  // never prepared: outside
    const double u = count_ > 1 ? std::clamp(double(t) * rate_ - a_, 0.0, 1.0) : 0.0;
    const Vec3d pd = p.cast<double>();
    Vec3d ga, gb, va, vb;
    const bool want_grad = grad || (vel && deforming());
    const double pa = fa_->sample(pd, want_grad ? &ga : nullptr, vel ? &va : nullptr);
    if (fb_ == fa_) {  // one frame: static, or held after the last
      if (grad) *grad = ga.cast<Real>();
      if (vel) *vel = Vec3::Zero();
      return Real(pa);
    }
    const double pb = fb_->sample(pd, want_grad ? &gb : nullptr, vel ? &vb : nullptr);
    const Vec3d g = (1 - u) * ga + u * gb;
    if (grad) *grad = g.cast<Real>();
    if (vel) {
      if (fa_->has_velocity() && fb_->has_velocity()) {
        *vel = ((1 - u) * va + u * vb).cast<Real>();
      } else {  // the level set's own motion along its normal: v = -(d phi / d t) n
        const double n = g.norm();
        *vel = n > 0 ? Vec3((-(pb - pa) * rate_ / n * g).cast<Real>()) : Vec3(Vec3::Zero());
      }
    }
    return Real((1 - u) * pa + u * pb);
  }

  std::size_t voxels() const override {
    std::size_t n = 0;
    for (const auto& f : loaded_) n += f.second->voxels();
    return n;
  }
  std::size_t bytes() const override {
    std::size_t n = 0;
    for (const auto& f : loaded_) n += f.second->bytes();
    return n;
  }

 private:
  void bracket(Real t, int& a, int& b, double& u) const {
    const double s = std::max(0.0, double(t) * rate_);
    a = int(std::min(std::floor(s), double(count_ - 1)));
    b = std::min(a + 1, count_ - 1);
    u = b == a ? 0.0 : s - a;
  }
  int count_;
  double rate_;
  Loader load_;
  std::map<int, std::shared_ptr<LevelSetFrame>> loaded_;
  const LevelSetFrame *fa_ = nullptr, *fb_ = nullptr;
  int a_ = 0;
};

}  // namespace

std::shared_ptr<ColliderField> make_mesh_field(std::shared_ptr<const TriangleMesh> mesh, double h) {
  {
    Vec3d lo, hi;
    mesh_bounds(*mesh, lo, hi);
    check_grid_range(lo, hi, h, "mesh collider");
  }
  auto frame = std::make_shared<MeshLevelSet>(std::move(mesh), std::vector<Vec3d>{}, h);
  return std::make_shared<FramedField>(1, 1.0, [frame](int) { return frame; });
}

std::shared_ptr<ColliderField> make_mesh_sequence_field(
    std::vector<std::shared_ptr<const TriangleMesh>> frames, double rate, double h) {
  for (const auto& m : frames) {
    Vec3d lo, hi;
    mesh_bounds(*m, lo, hi);
    check_grid_range(lo, hi, h, "mesh collider");
  }
  auto shared =
      std::make_shared<std::vector<std::shared_ptr<const TriangleMesh>>>(std::move(frames));
  const int count = int(shared->size());
  return std::make_shared<FramedField>(count, rate, [shared, rate, h](int k) {
    // Vertex velocities by central differences (one-sided at the ends): frame k's surface moves
    // at (x_{k+1} - x_{k-1}) rate / 2, carried to the voxels by the nearest point's barycentres.
    const auto& F = *shared;
    const int n = int(F.size());
    const int lo = std::max(0, k - 1), hi = std::min(n - 1, k + 1);
    std::vector<Vec3d> vv(F[size_t(k)]->vertices.size(), Vec3d::Zero());
    if (hi > lo)
      for (std::size_t i = 0; i < vv.size(); ++i)
        vv[i] = (F[size_t(hi)]->vertices[i] - F[size_t(lo)]->vertices[i]) * (rate / (hi - lo));
    return std::make_shared<MeshLevelSet>(F[size_t(k)], std::move(vv), h);
  });
}

std::shared_ptr<ColliderField> make_vdb_field(std::vector<std::string> files, std::string grid,
                                              double rate) {
  const int count = int(files.size());
  auto field = std::make_shared<FramedField>(
      count, rate, [files = std::move(files), grid = std::move(grid)](int k) {
        return std::make_shared<VdbFrame>(read_vdb(files[size_t(k)], grid));
      });
  return field;
}

std::string check_level_set_file(const std::string& path, const std::string& grid) {
  init_vdb();
  try {
    openvdb::io::File file(path);
    file.open(false);
    const auto meta = file.readAllGridMetadata();
    file.close();
    if (!find_level_set(*meta, grid)) return describe_missing(*meta, grid);
  } catch (const openvdb::Exception& e) {
    return std::string("cannot read it as a .vdb: ") + e.what();
  } catch (const std::bad_alloc&) {
    return "cannot read it as a .vdb: out of memory (corrupt file?)";
  }
  return "";
}

}  // namespace amalgam

namespace amalgam {

std::vector<std::array<std::int64_t, 3>> collider_blocks(const Vec3* x, std::size_t n, Real dx) {
  const double b = 8.0 * double(dx);
  std::vector<std::array<std::int64_t, 3>> keys;
  std::array<std::int64_t, 3> last{};
  for (std::size_t p = 0; p < n; ++p) {  // consecutive repeats dropped (sorted particles)
    std::array<std::int64_t, 3> k;
    for (int a = 0; a < 3; ++a) k[size_t(a)] = std::int64_t(std::floor(double(x[p][a]) / b));
    if (keys.empty() || k != last) keys.push_back(k), last = k;
  }
  std::sort(keys.begin(), keys.end());
  keys.erase(std::unique(keys.begin(), keys.end()), keys.end());
  return keys;
}

void prepare_collider_blocks(std::vector<Collider>& colliders,
                             const std::vector<std::array<std::int64_t, 3>>& keys, Real dx, Real t,
                             const exec::Space& space) {
  const double b = 8.0 * double(dx);
  std::vector<Box3> boxes;
  boxes.reserve(keys.size());
  const double halo = 4.0 * double(dx);
  for (const auto& k : keys) {
    const Vec3d lo = b * Vec3d(double(k[0]), double(k[1]), double(k[2]));
    boxes.push_back(Box3{lo - Vec3d::Constant(halo), lo + Vec3d::Constant(b + halo)});
  }
  for (Collider& c : colliders) c.prepare(boxes, t, space);
}

void prepare_colliders(std::vector<Collider>& colliders, const Vec3* x, std::size_t n, Real dx,
                       Real t, const exec::Space& space) {
  bool any = false;
  for (const Collider& c : colliders) any |= bool(c.field);
  if (!any) return;
  prepare_collider_blocks(colliders, collider_blocks(x, n, dx), dx, t, space);
}

}  // namespace amalgam
