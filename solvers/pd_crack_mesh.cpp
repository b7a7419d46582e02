#include "solvers/pd_crack_mesh.hpp"

#include <algorithm>
#include <map>
#include <numeric>
#include <stdexcept>

namespace amalgam {

namespace {
// Local vertex indices of the face opposite local vertex `o`.
constexpr std::uint8_t kFace[4][3] = {{1, 2, 3}, {0, 3, 2}, {0, 1, 3}, {0, 2, 1}};

std::uint32_t find(std::vector<std::uint32_t>& parent, std::uint32_t a) {
  while (parent[a] != a) a = parent[a] = parent[parent[a]];
  return a;
}
}  // namespace

PdCrackMesh::PdCrackMesh(const std::vector<Vec3d>& nodes,
                         const std::vector<std::array<std::int32_t, 4>>& tets,
                         std::uint32_t first_particle)
    : first_particle_(first_particle) {
  const std::size_t nt = tets.size();
  tets_.resize(nt);
  tet_faces_.resize(nt);
  outward_.resize(nt);
  x_.assign(4 * nt, Vec3::Zero());
  for (std::size_t v = 0; v < nodes.size(); ++v) x_[v] = nodes[v].cast<Real>();
  vertex_count_ = nodes.size();
  if (nodes.size() > x_.size()) x_.resize(nodes.size());  // unused nodes: keep them addressable
  // Faces by their sorted node triple.
  std::map<std::array<std::int32_t, 3>, std::uint32_t> index;
  for (std::size_t t = 0; t < nt; ++t) {
    for (int c = 0; c < 4; ++c) tets_[t][c] = std::uint32_t(tets[t][c]);
    const Vec3d c0 =
        (nodes[tets[t][0]] + nodes[tets[t][1]] + nodes[tets[t][2]] + nodes[tets[t][3]]) / 4;
    for (std::uint8_t o = 0; o < 4; ++o) {
      // Outward order: the normal points away from the tetrahedron's centre.
      std::array<std::uint8_t, 3> l = {kFace[o][0], kFace[o][1], kFace[o][2]};
      const Vec3d& a = nodes[tets[t][l[0]]];
      const Vec3d n = (nodes[tets[t][l[1]]] - a).cross(nodes[tets[t][l[2]]] - a);
      if (n.dot(a - c0) < 0) std::swap(l[1], l[2]);
      for (int k = 0; k < 3; ++k) outward_[t][3 * o + k] = l[k];
      std::array<std::int32_t, 3> key = {tets[t][kFace[o][0]], tets[t][kFace[o][1]],
                                         tets[t][kFace[o][2]]};
      std::sort(key.begin(), key.end());
      auto it = index.find(key);
      if (it == index.end()) {
        Face f;
        f.tet[0] = std::uint32_t(t);
        f.tet[1] = ~std::uint32_t(0);
        f.local[0] = o;
        f.local[1] = 0;
        index.emplace(key, std::uint32_t(faces_.size()));
        tet_faces_[t][o] = std::uint32_t(faces_.size());
        faces_.push_back(f);
      } else {
        Face& f = faces_[it->second];
        if (f.tet[1] != ~std::uint32_t(0))
          throw std::invalid_argument(
              "tetrahedral mesh: a face is shared by more than two tetrahedra");
        f.tet[1] = std::uint32_t(t);
        f.local[1] = o;
        tet_faces_[t][o] = it->second;
      }
    }
  }
  cracked_.assign(faces_.size(), 0);
  rebuild_incidence();
}

void PdCrackMesh::rebuild_incidence() {
  incident_.assign(x_.size(), {});
  for (std::uint32_t t = 0; t < tets_.size(); ++t)
    for (std::uint32_t v : tets_[t]) incident_[v].push_back(t);
}

std::uint64_t PdCrackMesh::find_bond(const PdBonds& bonds, const Face& f) const {
  const std::uint32_t i = first_particle_ + f.tet[0], j = first_particle_ + f.tet[1];
  if (std::size_t(i) >= bonds.particles() || std::size_t(j) >= bonds.particles())
    throw std::logic_error("PdCrackMesh: tetrahedron without a particle");
  const std::uint32_t* b = bonds.neighbor.data() + bonds.offsets[i];
  const std::uint32_t* e = bonds.neighbor.data() + bonds.offsets[i + 1];
  const std::uint32_t* p = std::lower_bound(b, e, j);
  return p != e && *p == j ? bonds.offsets[i] + std::uint64_t(p - b) : kNone;
}

void PdCrackMesh::attach(const PdBonds& bonds) {
  for (Face& f : faces_) f.bond = f.tet[1] == ~std::uint32_t(0) ? kNone : find_bond(bonds, f);
  update_topology(bonds);
}

void PdCrackMesh::reattach(const PdBonds& bonds) {
  for (std::size_t k = 0; k < faces_.size(); ++k) {
    Face& f = faces_[k];
    if (f.bond == kNone) continue;  // a boundary face, or a pair without a bond: never cracks
    if (cracked_[k]) {
      f.bond = kNone;  // done with it (its bond may be gone)
      continue;
    }
    f.bond = find_bond(bonds, f);
    if (f.bond == kNone) throw std::logic_error("PdCrackMesh: an uncracked face lost its bond");
  }
}

std::size_t PdCrackMesh::update_topology(const PdBonds& bonds) {
  const std::uint64_t before = vertex_count_;
  std::vector<std::uint32_t> candidates;
  for (std::size_t k = 0; k < faces_.size(); ++k) {
    const Face& f = faces_[k];
    if (cracked_[k] || f.bond == kNone || bonds.intact[f.bond]) continue;
    cracked_[k] = 1;
    for (std::uint8_t c : kFace[f.local[0]]) candidates.push_back(tets_[f.tet[0]][c]);
  }
  std::sort(candidates.begin(), candidates.end());
  candidates.erase(std::unique(candidates.begin(), candidates.end()), candidates.end());
  for (std::uint32_t v : candidates) split_vertex(v);
  return std::size_t(vertex_count_ - before);
}

void PdCrackMesh::split_vertex(std::uint32_t v) {
  const std::vector<std::uint32_t> inc = incident_[v];  // sorted: tets are appended in order
  if (inc.size() < 2) return;
  std::vector<std::uint32_t> parent(inc.size());
  std::iota(parent.begin(), parent.end(), 0u);
  auto slot = [&](std::uint32_t t) {
    return std::uint32_t(std::lower_bound(inc.begin(), inc.end(), t) - inc.begin());
  };
  for (std::uint32_t a = 0; a < inc.size(); ++a) {
    const std::uint32_t t = inc[a];
    for (std::uint8_t o = 0; o < 4; ++o) {
      if (tets_[t][o] == v) continue;  // the face opposite v does not contain it
      const std::uint32_t fi = tet_faces_[t][o];
      const Face& f = faces_[fi];
      if (cracked_[fi] || f.tet[1] == ~std::uint32_t(0)) continue;
      const std::uint32_t u = f.tet[0] == t ? f.tet[1] : f.tet[0];
      const std::uint32_t b = slot(u);
      if (b < inc.size() && inc[b] == u) parent[find(parent, a)] = find(parent, b);
    }
  }
  // Groups in order of their lowest tetrahedron; the first keeps v.
  std::vector<std::uint32_t> root_vertex(inc.size(), ~std::uint32_t(0));
  const std::uint32_t keep = find(parent, 0);
  root_vertex[keep] = v;
  std::vector<std::uint32_t> kept;
  for (std::uint32_t a = 0; a < inc.size(); ++a) {
    const std::uint32_t r = find(parent, a);
    if (root_vertex[r] == ~std::uint32_t(0)) {
      if (vertex_count_ >= x_.size())
        throw std::logic_error("PdCrackMesh: vertex capacity exceeded");
      root_vertex[r] = std::uint32_t(vertex_count_);
      x_[vertex_count_] = x_[v];
      ++vertex_count_;
    }
    const std::uint32_t nv = root_vertex[r];
    if (nv == v) {
      kept.push_back(inc[a]);
      continue;
    }
    for (std::uint32_t& c : tets_[inc[a]])
      if (c == v) c = nv;
    incident_[nv].push_back(inc[a]);
  }
  incident_[v] = kept;
}

void PdCrackMesh::vertex_velocities(const Vec3* v, const Real* volume, const std::int32_t* material,
                                    const PdMaterial* materials, std::vector<double>& weight,
                                    std::vector<Vec3d>& velocity) const {
  const std::size_t nv = std::size_t(vertex_count_);
  weight.assign(nv, 0.0);
  velocity.assign(nv, Vec3d::Zero());
  for (std::size_t t = 0; t < tets_.size(); ++t) {  // eqs. 19, 20: 1/4 m_p per incident tetrahedron
    const std::size_t p = first_particle_ + t;
    const double m = 0.25 * double(materials[material[p]].density) * double(volume[p]);
    for (std::uint32_t c : tets_[t]) {
      weight[c] += m;
      velocity[c] += m * v[p].cast<double>();
    }
  }
  for (std::size_t k = 0; k < nv; ++k)
    if (weight[k] > 0) velocity[k] = velocity[k] / weight[k];
}

void PdCrackMesh::move_vertices(const Vec3* v, const Real* volume, const std::int32_t* material,
                                const PdMaterial* materials, Real dt) {
  vertex_velocities(v, volume, material, materials, weight_, velocity_);
  for (std::size_t k = 0; k < std::size_t(vertex_count_); ++k)  // eq. 21
    if (weight_[k] > 0) x_[k] += (dt * velocity_[k]).cast<Real>();
}

void PdCrackMesh::surface(std::vector<Vec3>& vertices,
                          std::vector<std::array<std::uint32_t, 3>>& triangles,
                          std::vector<std::uint8_t>& crack,
                          const std::vector<Vec3d>* vertex_velocity,
                          std::vector<Vec3>* velocity) const {
  vertices.clear();
  triangles.clear();
  crack.clear();
  if (velocity) velocity->clear();
  std::vector<std::uint32_t> remap(std::size_t(vertex_count_), ~std::uint32_t(0));
  auto emit = [&](std::uint32_t t, std::uint8_t o, std::uint8_t is_crack) {
    std::array<std::uint32_t, 3> tri;
    for (int k = 0; k < 3; ++k) {
      const std::uint32_t g = tets_[t][outward_[t][3 * o + k]];
      if (remap[g] == ~std::uint32_t(0)) {
        remap[g] = std::uint32_t(vertices.size());
        vertices.push_back(x_[g]);
        if (velocity && vertex_velocity) velocity->push_back((*vertex_velocity)[g].cast<Real>());
      }
      tri[k] = remap[g];
    }
    triangles.push_back(tri);
    crack.push_back(is_crack);
  };
  for (std::size_t k = 0; k < faces_.size(); ++k) {
    const Face& f = faces_[k];
    if (f.tet[1] == ~std::uint32_t(0)) emit(f.tet[0], f.local[0], 0);
  }
  for (std::size_t k = 0; k < faces_.size(); ++k) {
    if (!cracked_[k]) continue;
    const Face& f = faces_[k];
    emit(f.tet[0], f.local[0], 1);
    emit(f.tet[1], f.local[1], 1);
  }
}

std::size_t PdCrackMesh::crack_faces() const {
  return std::size_t(std::count(cracked_.begin(), cracked_.end(), std::uint8_t(1)));
}

std::vector<PdCrackMesh::StateArray> PdCrackMesh::state() {
  return {{"vertex_count", reinterpret_cast<char*>(&vertex_count_), sizeof vertex_count_},
          {"positions", reinterpret_cast<char*>(x_.data()), x_.size() * sizeof(Vec3)},
          {"tets", reinterpret_cast<char*>(tets_.data()), tets_.size() * sizeof(tets_[0])},
          {"cracked", reinterpret_cast<char*>(cracked_.data()), cracked_.size()}};
}

}  // namespace amalgam
