#include "solvers/particle_domains.hpp"

#include <cmath>
#include <limits>
#include <sstream>
#include <unordered_map>

#include "core/errors.hpp"
#include "kernels/mpm_transfers.hpp"

namespace amalgam {

DomainAttributes DomainAttributes::add_to(ParticleSet& ps) {
  DomainAttributes a;
  a.corners = ps.add("domain_corners", AttrType::Int32, 8);
  a.h = ps.add("domain_h", AttrType::Real, 3);
  a.state = ps.add("domain_state", AttrType::Int32, 1);
  return a;
}

ParticleDomains::ParticleDomains() {
  cx_ = corners_.add("x", AttrType::Real, 3);
  cm_ = corners_.add("m", AttrType::Real, 1);
  cp_ = corners_.add("p", AttrType::Real, 3);
  cf_ = corners_.add("f", AttrType::Real, 3);
  cv_ = corners_.add("v", AttrType::Real, 3);
  cdv_ = corners_.add("dv", AttrType::Real, 3);
  cenr_ = corners_.add("enriched", AttrType::Int32, 1);
  px_ = points_.add("x", AttrType::Real, 3);
  pm_ = points_.add("m", AttrType::Real, 1);
  pp_ = points_.add("p", AttrType::Real, 3);
  pf_ = points_.add("f", AttrType::Real, 3);
  pcorner_ = points_.add("corner", AttrType::Int32, 1);
  pstress_ = points_.add("stress", AttrType::Real, 9);
}

void ParticleDomains::add_object(
    ParticleSet& ps, const DomainAttributes& da, ParticleSet::Id x_id, std::size_t first, Real h,
    const std::vector<Vec3d>* surface_vertices,
    const std::vector<std::array<std::int32_t, 3>>* surface_triangles) {
  const std::size_t n = ps.size();
  if (first >= n) return;
  if (!(h > 0)) throw InputError("particle domains: lattice spacing must be positive");
  const Vec3* x = ps.vec3(x_id);
  Vec3d lo = x[first].cast<double>();
  for (std::size_t p = first; p < n; ++p) lo = lo.cwiseMin(x[p].cast<double>());
  // Lattice coordinates of every particle; corners are lattice points (i + b), b in {0,1}^3.
  const double hd = double(h);
  std::unordered_map<std::uint64_t, std::int32_t> index;
  index.reserve((n - first) * 2);
  std::int32_t* corners = ps.int32(da.corners);
  Vec3* hp = ps.vec3(da.h);
  std::int32_t* state = ps.int32(da.state);
  std::vector<Vec3> new_x;
  const std::size_t c0 = corners_.size();
  std::unordered_map<std::uint64_t, std::int32_t> cell;  // lattice cell -> particle (for embedding)
  for (std::size_t p = first; p < n; ++p) {
    const Vec3d s = (x[p].cast<double>() - lo) / hd;
    const Vec3d r = s.array().round();
    if ((s - r).cwiseAbs().maxCoeff() > 1e-3 || r.maxCoeff() >= double(1 << 20)) {
      std::ostringstream os;
      os << "particle domains need particles on a lattice (\"jitter\": 0): particle " << p << " is "
         << (s - r).cwiseAbs().maxCoeff() << " spacings off the lattice";
      throw InputError(os.str());
    }
    cell.emplace((std::uint64_t(r[0]) << 42) | (std::uint64_t(r[1]) << 21) | std::uint64_t(r[2]),
                 std::int32_t(p));
    for (int slot = 0; slot < 8; ++slot) {
      const std::uint64_t i = std::uint64_t(r[0]) + ((slot >> 2) & 1),
                          j = std::uint64_t(r[1]) + ((slot >> 1) & 1),
                          k = std::uint64_t(r[2]) + (slot & 1);
      const std::uint64_t key = (i << 42) | (j << 21) | k;
      auto it = index.find(key);
      if (it == index.end()) {
        it = index.emplace(key, std::int32_t(c0 + new_x.size())).first;
        new_x.push_back(
            (lo + hd * Vec3d(double(i) - 0.5, double(j) - 0.5, double(k) - 0.5)).cast<Real>());
      }
      corners[8 * p + std::size_t(slot)] = it->second;
    }
    hp[p] = Vec3::Constant(h);
    state[p] = kUnenriched;
  }
  corners_.resize(c0 + new_x.size());
  Vec3* cx = corners_.vec3(cx_);
  for (std::size_t a = 0; a < new_x.size(); ++a) cx[c0 + a] = new_x[a];

  if (surface_vertices && surface_triangles) {
    // Embedded surface (Sec. 4.1): vertex -> the domain containing it, else the nearest domain
    // centre within two spacings; xi = (X - X_p) / (h / 2) are its trilinear coordinates there
    // (outside [-1, 1]^3 for a vertex beyond the sampled lattice: trilinear extrapolation).
    const std::uint32_t v0 = std::uint32_t(surf_particle_.size());
    for (std::size_t k = 0; k < surface_vertices->size(); ++k) {
      const Vec3d X = (*surface_vertices)[k];
      const Vec3d s = (X - lo) / hd;
      const Vec3i r0(int(std::lround(s[0])), int(std::lround(s[1])), int(std::lround(s[2])));
      std::int32_t best = -1;
      double best_d = 1e300;
      for (int ring = 0; ring <= 2 && best < 0; ++ring)
        for (int i = -ring; i <= ring; ++i)
          for (int j = -ring; j <= ring; ++j)
            for (int l = -ring; l <= ring; ++l) {
              const Vec3i r = r0 + Vec3i(i, j, l);
              if (r.minCoeff() < 0) continue;
              const auto it = cell.find((std::uint64_t(r[0]) << 42) | (std::uint64_t(r[1]) << 21) |
                                        std::uint64_t(r[2]));
              if (it == cell.end()) continue;
              const double d = (x[it->second].cast<double>() - X).squaredNorm();
              if (d < best_d) best_d = d, best = it->second;
            }
      if (best < 0) {
        std::ostringstream os;
        os << "embedded surface: vertex " << k << " at (" << X.transpose()
           << ") is more than two lattice spacings from every particle of its object";
        throw InputError(os.str());
      }
      surf_particle_.push_back(best);
      surf_xi_.push_back(((X - x[best].cast<double>()) / (0.5 * hd)).cast<Real>());
    }
    for (const auto& t : *surface_triangles)
      surf_tris_.push_back(
          {v0 + std::uint32_t(t[0]), v0 + std::uint32_t(t[1]), v0 + std::uint32_t(t[2])});
  }

  // Corner -> particle adjacency (CSR), over every particle (counting sort: particles in order).
  const std::size_t nc = corners_.size();
  adj_start_.assign(nc + 1, 0);
  for (std::size_t p = 0; p < n; ++p)
    for (int s = 0; s < 8; ++s) ++adj_start_[std::size_t(corners[8 * p + std::size_t(s)]) + 1];
  for (std::size_t a = 0; a < nc; ++a) adj_start_[a + 1] += adj_start_[a];
  adj_.assign(adj_start_[nc], 0);
  std::vector<std::uint32_t> fill(adj_start_.begin(), adj_start_.end() - 1);
  for (std::size_t p = 0; p < n; ++p)
    for (int s = 0; s < 8; ++s)
      adj_[fill[std::size_t(corners[8 * p + std::size_t(s)])]++] =
          std::uint32_t(p << 3) | std::uint32_t(s);
}

void ParticleDomains::surface(const std::int32_t* particle_corners, std::vector<Vec3>& vertices,
                              std::vector<std::array<std::uint32_t, 3>>& triangles) const {
  const Vec3* cx = corners_.vec3(cx_);
  vertices.resize(surf_particle_.size());
  for (std::size_t k = 0; k < surf_particle_.size(); ++k) {
    const std::int32_t* c = particle_corners + 8 * std::size_t(surf_particle_[k]);
    const Vec3& xi = surf_xi_[k];
    Vec3 x = Vec3::Zero();
    for (int slot = 0; slot < 8; ++slot) {  // x = sum_a N_a(xi) x_a, trilinear N_a
      const Real n = ((slot >> 2) & 1 ? 1 + xi[0] : 1 - xi[0]) *
                     ((slot >> 1) & 1 ? 1 + xi[1] : 1 - xi[1]) *
                     (slot & 1 ? 1 + xi[2] : 1 - xi[2]) / 8;
      x += n * cx[std::size_t(c[slot])];
    }
    vertices[k] = x;
  }
  triangles = surf_tris_;
}

void ParticleDomains::surface_velocity(const Vec3* particle_v, std::vector<Vec3>& velocity) const {
  velocity.resize(surf_particle_.size());
  for (std::size_t k = 0; k < surf_particle_.size(); ++k)
    velocity[k] = particle_v[std::size_t(surf_particle_[k])];
}

std::size_t ParticleDomains::disable_melted(const exec::Space& space, const DomainParticleView& p,
                                            const MaterialParams* materials) {
  disabled_ = domain_disable_melted(space, p, materials);
  return disabled_;
}

DomainCornerView ParticleDomains::corner_view() {
  return {corners_.vec3(cx_), corners_.real(cm_),  corners_.vec3(cp_),    corners_.vec3(cf_),
          corners_.vec3(cv_), corners_.vec3(cdv_), corners_.int32(cenr_), adj_start_.data(),
          adj_.data(),        corners_.size()};
}
DomainPointView ParticleDomains::point_view() {
  DomainPointView v{points_.vec3(px_), points_.real(pm_),       points_.vec3(pp_),
                    points_.vec3(pf_), points_.int32(pcorner_), points_.size()};
  v.stress = points_.mat3(pstress_);
  return v;
}

void ParticleDomains::stresses_and_enrichment(const exec::Space& space, const DomainParticleView& p,
                                              const DomainParams& prm, bool hessians, bool psd,
                                              bool gauss_quadrature) {
  piola_.resize(p.n);
  smin_.resize(p.n);
  if (hessians) hess_.resize(p.n);
  domain_stresses(space, p, prm, piola_.data(), hessians ? hess_.data() : nullptr, psd,
                  smin_.data());
  last_counts_ = domain_mark_enrichment(space, p, corner_view());
  const double live =
      double(last_counts_.unenriched + last_counts_.transitional + last_counts_.enriched);
  const double fe = live > 0 ? double(last_counts_.enriched) / live : 0.0;
  counters_.steps += 1;
  counters_.enriched_fraction_sum += fe;
  counters_.transitional_fraction_sum += live > 0 ? double(last_counts_.transitional) / live : 0.0;
  counters_.max_enriched_fraction = std::max(counters_.max_enriched_fraction, fe);
  counters_.last_enriched_corners = last_counts_.corners;

  // The transitional and enriched particles, listed in particle order (deterministic).
  quad_index_.resize(p.n);  // written below when anything is listed; unused (null view) otherwise
  quad_hessians_ = hessians;
  std::size_t nq = 0;
  if (gauss_quadrature && last_counts_.transitional + last_counts_.enriched > 0) {
    quad_scan_.resize(p.n);
    const std::int32_t* state = p.state;
    nq = exec::parallel_scan<std::uint32_t>(
        space, "domain.quadrature_scan", exec::Index(p.n),
        [=](exec::Index i) { return std::uint32_t(state[i] >= kTransitional); }, quad_scan_.data());
    quad_list_.resize(nq);
    std::int32_t* index = quad_index_.data();
    std::uint32_t* list = quad_list_.data();
    const std::uint32_t* scan = quad_scan_.data();
    exec::parallel_for(space, "domain.quadrature_list", exec::Index(p.n), [=](exec::Index i) {
      if (state[i] < kTransitional) {
        index[i] = -1;
        return;
      }
      index[i] = std::int32_t(scan[i]);
      list[scan[i]] = std::uint32_t(i);
    });
  }
  quad_list_.resize(nq);
  quad_piola_.resize(8 * nq);
  quad_scratch_.resize(hessians ? 8 * nq : 0);
  quad_hess_.resize(hessians ? 8 * nq : 0);
  if (nq > 0) domain_quadrature_stresses(space, p, corner_view(), prm, quadrature_view(), psd);
}

DomainQuadrature ParticleDomains::quadrature_view() {
  DomainQuadrature q;
  q.index = quad_list_.empty() ? nullptr : quad_index_.data();  // null: every particle one-point
  q.particles = quad_list_.data();
  q.n = quad_list_.size();
  q.piola = quad_piola_.data();
  q.hess = quad_hessians_ ? quad_hess_.data() : nullptr;
  q.scratch = quad_hessians_ ? quad_scratch_.data() : nullptr;
  return q;
}

void ParticleDomains::particles_to_corners(const exec::Space& space, const DomainParticleView& p) {
  domain_particles_to_corners(space, p, corner_view(), piola_.data(), quadrature_view());
}

Real ParticleDomains::enriched_dt_limit(const exec::Space& space, const std::int32_t* state,
                                        const Vec3* h, Real cfl, Real wave_speed) const {
  if (smin_.empty() || !(wave_speed > 0)) return std::numeric_limits<Real>::infinity();
  const Real* smin = smin_.data();
  const Real inf = std::numeric_limits<Real>::infinity();
  return exec::parallel_reduce(
      space, "domain.dt_limit", exec::Index(smin_.size()), inf,
      [=](exec::Index i, Real& acc) {
        if (state[i] < kTransitional) return;
        // An enriched corner is an FE node of spacing s h whose wave speed grows like c / s under
        // compression (neo-Hookean / fixed corotated stiffness ~ 1/s^2): dt <= cfl s^2 h / c.
        const Real s = smin[i];
        acc = std::min(acc, cfl * s * s * h[i].minCoeff() / wave_speed);
      },
      [](Real a, Real b) { return std::min(a, b); });
}

void ParticleDomains::corners_to_grid(const exec::Space& space, const DomainParticleView& p,
                                      const DomainParams& prm, SparseGrid& grid, Real dx) {
  const DomainCornerView c = corner_view();
  point_start_.resize(c.n);
  const std::size_t nc = domain_point_offsets(space, c, point_start_.data());
  // Disabled particles (Sec. 8) join the points after the corners, as plain MPM points (counted
  // from the states every substep: they come back from a checkpoint with the particles).
  particle_start_.resize(p.n);
  const std::size_t nd = domain_particle_point_offsets(space, p, particle_start_.data());
  disabled_ = nd;
  points_.resize(nc + nd);
  domain_collect_points(space, c, point_start_.data(), point_view());
  if (nd > 0)
    domain_collect_particle_points(space, p, prm, particle_start_.data(), nc, point_view());
  binning_.sort_and_bin(space, points_, px_, dx, 2, bins_);  // quadratic keys (see the kernels)
  grid.update_topology(space, bins_);
  domain_points_to_grid(space, point_view(),
                        make_grid_view(grid, bins_, grid.node4(0), grid.node4(1)), dx);
}

std::size_t ParticleDomains::number_enriched_dofs(const exec::Space& space) {
  const DomainCornerView c = corner_view();
  dof_.resize(c.n);
  dof_scan_.resize(c.n);
  const Real* m = c.m;
  const std::int32_t* enr = c.enriched;
  enriched_dofs_ = exec::parallel_scan<std::uint32_t>(
      space, "domain.dof_scan", exec::Index(c.n),
      [=](exec::Index i) { return std::uint32_t(enr[i] && m[i] > 0); }, dof_scan_.data());
  std::int32_t* dof = dof_.data();
  const std::uint32_t* st = dof_scan_.data();
  exec::parallel_for(space, "domain.dofs", exec::Index(c.n), [=](exec::Index i) {
    dof[i] = enr[i] && m[i] > 0 ? std::int32_t(st[i]) : -1;
  });
  return enriched_dofs_;
}

void ParticleDomains::update_enriched_corners(const exec::Space& space, const DomainParams& prm) {
  domain_update_enriched_corners(space, corner_view(), prm);
}

void ParticleDomains::enriched_to_dofs(const exec::Space& space, Real* mass, Real* v) {
  const DomainCornerView c = corner_view();
  const std::int32_t* dof = dof_.data();
  exec::parallel_for(space, "domain.enriched_to_dofs", exec::Index(c.n), [=](exec::Index a) {
    const std::int32_t d = dof[a];
    if (d < 0) return;
    mass[d] = c.m[a];
    for (int k = 0; k < 3; ++k) v[4 * std::size_t(d) + std::size_t(k)] = c.v[a][k];
    v[4 * std::size_t(d) + 3] = 0;
  });
}

void ParticleDomains::dofs_to_enriched(const exec::Space& space, const Real* v) {
  const DomainCornerView c = corner_view();
  const std::int32_t* dof = dof_.data();
  exec::parallel_for(space, "domain.dofs_to_enriched", exec::Index(c.n), [=](exec::Index a) {
    const std::int32_t d = dof[a];
    if (d < 0) return;
    const Real* s = v + 4 * std::size_t(d);
    c.v[a] = Vec3(s[0], s[1], s[2]);
    c.dv[a] = c.v[a] - c.p[a] / c.m[a];
  });
}

void ParticleDomains::grid_to_corners(const exec::Space& space, const MpmGridView& g,
                                      const DomainParticleView& p, const DomainParams& prm) {
  const DomainCornerView c = corner_view();
  domain_grid_to_corners(space, point_view(), g, prm.dx, c, p, prm);
  domain_collide_corners(space, c, prm);
}

void ParticleDomains::corners_to_particles(const exec::Space& space, const DomainParticleView& p,
                                           const DomainParams& prm) {
  const DomainCornerView c = corner_view();
  domain_corners_to_particles(space, p, c, prm);
  domain_advect(space, p, c, prm);
}

void ParticleDomains::hessian_action(const exec::Space& space, const DomainParticleView& p,
                                     const MpmGridView& g, Real dx, const Real* du_grid,
                                     const Real* du_corner, Real scale, Real* out_grid,
                                     Real* out_corner) {
  const DomainCornerView c = corner_view();
  const DomainPointView pts = point_view();
  du_c_.resize(c.n);
  df_c_.resize(c.n);
  dP_.resize(p.n);
  domain_corner_increments(space, pts, g, dx, du_grid, c, dof_.data(), du_corner, du_c_.data());
  domain_corner_hessian_forces(space, p, c, hess_.data(), quadrature_view(), du_c_.data(),
                               dP_.data(), df_c_.data());
  domain_forces_to_dofs(space, pts, g, dx, c, dof_.data(), df_c_.data(), scale, out_grid,
                        out_corner);
}

void ParticleDomains::hessian_diagonal(const exec::Space& space, const DomainParticleView& p,
                                       const MpmGridView& g, Real dx, Real scale, Real* diag_grid,
                                       Real* diag_corner) {
  const DomainCornerView c = corner_view();
  df_c_.resize(c.n);
  domain_corner_hessian_diagonal(space, p, c, hess_.data(), quadrature_view(), df_c_.data());
  domain_diagonal_to_dofs(space, point_view(), g, dx, c, dof_.data(), df_c_.data(), scale,
                          diag_grid, diag_corner);
}

}  // namespace amalgam
