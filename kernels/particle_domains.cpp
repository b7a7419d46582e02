#include "kernels/particle_domains.hpp"

#include <algorithm>
#include <cmath>

#include "core/math/bspline.hpp"
#include "core/math/svd3.hpp"
#include "kernels/grid_block.hpp"

namespace amalgam {

Real domain_reference_weights(const Vec3 X[8], Real omega[8], Vec3 grad[8]) {
  // Trilinear N_a(xi) = prod_k (1 + s_k xi_k) / 2 on [-1, 1]^3, Gauss points +-1/sqrt(3).
  const Real g = Real(1) / std::sqrt(Real(3));
  Real V = 0;
  for (int a = 0; a < 8; ++a) omega[a] = 0, grad[a].setZero();
  for (int q = 0; q < 8; ++q) {
    const Vec3 xi(((q >> 2) & 1) ? g : -g, ((q >> 1) & 1) ? g : -g, (q & 1) ? g : -g);
    Real N[8];
    Vec3 dN[8];  // d N / d xi
    for (int a = 0; a < 8; ++a) {
      const Vec3 s(((a >> 2) & 1) ? 1 : -1, ((a >> 1) & 1) ? 1 : -1, (a & 1) ? 1 : -1);
      const Vec3 t = (Vec3::Ones() + s.cwiseProduct(xi)) / 2;
      N[a] = t[0] * t[1] * t[2];
      dN[a] = Vec3(s[0] / 2 * t[1] * t[2], t[0] * s[1] / 2 * t[2], t[0] * t[1] * s[2] / 2);
    }
    Mat3 J = Mat3::Zero();  // dX / dxi
    for (int a = 0; a < 8; ++a) J += X[a] * dN[a].transpose();
    const Real detJ = J.determinant();  // Gauss weights are 1
    const Mat3 JinvT = J.inverse().transpose();
    V += detJ;
    for (int a = 0; a < 8; ++a) {
      omega[a] += N[a] * detJ;
      grad[a] += (JinvT * dN[a]) * detJ;
    }
  }
  for (int a = 0; a < 8; ++a) omega[a] /= V, grad[a] /= V;
  return V;
}

namespace {

struct ClampedSvd {
  Svd3<Real> d;
  Vec3 s;  // clamped singular values
};
inline ClampedSvd clamped_svd(const Mat3& F, Real clamp) {
  ClampedSvd c{svd3(F), Vec3::Zero()};
  c.s = c.d.sigma.cwiseMax(clamp);  // an inverted F has a negative last singular value
  return c;
}

}  // namespace

void domain_stresses(const exec::Space& space, const DomainParticleView& p, const DomainParams& prm,
                     Mat3* piola, DomainHessian* hess, bool psd, Real* smin) {
  const MaterialParams* mats = prm.materials;
  exec::parallel_for(space, "domain.stress", exec::Index(p.n), [&](exec::Index i) {
    if (p.state[i] == kDomainDisabled) {
      piola[i].setZero();
      smin[i] = 1;
      return;
    }
    const ClampedSvd c = clamped_svd(p.F[i], prm.clamp);
    // Enrichment criterion (eq. 10), or a flattened / inverted domain; state 3 marks it for
    // domain_mark_enrichment.
    p.state[i] = prm.enrichment && (enrichment_metric(c.s) <= prm.epsilon ||
                                    c.d.sigma.minCoeff() <= prm.clamp)
                     ? 3
                     : kUnenriched;
    smin[i] = c.s.minCoeff();
    Vec3 ps = Vec3::Zero();
    Mat3 H = Mat3::Zero();
    if (prm.elastic)
      mats[p.material[i]].sigma_derivatives(c.s, p.plastic ? p.plastic[i] : Real(0),
                                            p.temperature ? p.temperature[i] : Real(0), ps, H);
    piola[i] = c.d.U * ps.asDiagonal() * c.d.V.transpose();  // P = U P(S) V^T (Sec. 5.3)
    if (hess) {
      DomainHessian& dh = hess[i];
      dh.U = c.d.U;
      dh.V = c.d.V;
      dh.h = SvdFrameHessian<Real>::from(c.s, ps, H);
      if (psd) dh.h.make_psd();
      dh.V0 = p.volume0[i];
    }
  });
}

EnrichmentCounts domain_mark_enrichment(const exec::Space& space, const DomainParticleView& p,
                                        const DomainCornerView& c) {
  // corners of a particle marked by domain_stresses (state 3) are enriched
  std::int32_t* state = p.state;
  const std::uint32_t* as = c.adj_start;
  const std::uint32_t* adj = c.adj;
  std::int32_t* enr = c.enriched;
  const std::size_t ncorner = exec::parallel_reduce(
      space, "domain.mark_corners", exec::Index(c.n), std::size_t(0),
      [=](exec::Index a, std::size_t& acc) {
        std::int32_t e = 0;
        for (std::uint32_t k = as[a]; k < as[a + 1]; ++k) e |= state[adj[k] >> 3] == 3 ? 1 : 0;
        enr[a] = e;
        acc += std::size_t(e);
      },
      [](std::size_t x, std::size_t y) { return x + y; });
  // particle states from their corners
  const std::int32_t* corners = p.corners;
  struct Acc {
    std::size_t n[3] = {0, 0, 0};
  };
  const Acc cnt = exec::parallel_reduce(
      space, "domain.states", exec::Index(p.n), Acc{},
      [=](exec::Index i, Acc& acc) {
        if (state[i] == kDomainDisabled) return;
        int k = 0;
        for (int s = 0; s < 8; ++s) k += enr[corners[8 * i + s]];
        state[i] = k == 0 ? kUnenriched : k == 8 ? kEnriched : kTransitional;
        ++acc.n[state[i]];
      },
      [](Acc x, const Acc& y) {
        for (int k = 0; k < 3; ++k) x.n[k] += y.n[k];
        return x;
      });
  return {cnt.n[0], cnt.n[1], cnt.n[2], ncorner};
}

namespace {
// Calls fn(grad, k) for the integration points of particle q's corner `slot`: the one-point
// gradient grad_X omega_ap (k = -1, weight V0), or for a listed particle each Gauss point's
// grad N_a(xi_g) (k = 8 e + g, the entry's slot for that point, weight V0 / 8).
template <class Fn>
inline void for_each_point(const DomainParticleView& p, const DomainQuadrature& quad, std::size_t q,
                           int slot, Fn&& fn) {
  const std::int32_t e = quad.index ? quad.index[q] : -1;
  if (e < 0) {
    fn(box_corner_gradient(slot, p.h[q]), std::ptrdiff_t(-1));
    return;
  }
  for (int g = 0; g < 8; ++g) fn(box_gauss_gradient(slot, g, p.h[q]), std::ptrdiff_t(8 * e + g));
}

// Elastic force of particle q on its corner `slot` (eq. 8): -V0 P grad omega_ap, or for a listed
// particle the eight-point sum -(V0 / 8) sum_g P_g grad N_a(xi_g).
inline Vec3 corner_force(const DomainParticleView& p, const Mat3* piola,
                         const DomainQuadrature& quad, std::size_t q, int slot) {
  Vec3 f = Vec3::Zero();
  for_each_point(p, quad, q, slot, [&](const Vec3& grad, std::ptrdiff_t k) {
    f -= k < 0 ? p.volume0[q] * (piola[q] * grad) : (p.volume0[q] / 8) * (quad.piola[k] * grad);
  });
  return f;
}
}  // namespace

void domain_quadrature_stresses(const exec::Space& space, const DomainParticleView& p,
                                const DomainCornerView& c, const DomainParams& prm,
                                const DomainQuadrature& quad, bool psd) {
  const MaterialParams* mats = prm.materials;
  exec::parallel_for(space, "domain.quadrature_stress", exec::Index(quad.n), [&](exec::Index e) {
    const std::size_t i = quad.particles[e];
    const std::int32_t* cn = p.corners + 8 * i;
    for (int g = 0; g < 8; ++g) {
      Mat3 F = Mat3::Zero();  // F_g = sum_a x_a (grad_X N_a(xi_g))^T
      for (int a = 0; a < 8; ++a)
        F += c.x[std::size_t(cn[a])] * box_gauss_gradient(a, g, p.h[i]).transpose();
      const ClampedSvd d = clamped_svd(F, prm.clamp);
      Vec3 ps = Vec3::Zero();
      Mat3 H = Mat3::Zero();
      if (prm.elastic)
        mats[p.material[i]].sigma_derivatives(d.s, p.plastic ? p.plastic[i] : Real(0),
                                              p.temperature ? p.temperature[i] : Real(0), ps, H);
      quad.piola[8 * std::size_t(e) + std::size_t(g)] = d.d.U * ps.asDiagonal() * d.d.V.transpose();
      if (quad.hess) {
        DomainHessian& dh = quad.hess[8 * std::size_t(e) + std::size_t(g)];
        dh.U = d.d.U;
        dh.V = d.d.V;
        dh.h = SvdFrameHessian<Real>::from(d.s, ps, H);
        if (psd) dh.h.make_psd();
        dh.V0 = p.volume0[i] / 8;
      }
    }
  });
}

void domain_particles_to_corners(const exec::Space& space, const DomainParticleView& p,
                                 const DomainCornerView& c, const Mat3* piola,
                                 const DomainQuadrature& quad) {
  exec::parallel_for(space, "domain.p2c", exec::Index(c.n), [&](exec::Index a) {
    Real m = 0;
    Vec3 mv = Vec3::Zero(), f = Vec3::Zero();
    for (std::uint32_t k = c.adj_start[a]; k < c.adj_start[a + 1]; ++k) {
      const std::size_t q = c.adj[k] >> 3;
      if (p.state[q] == kDomainDisabled) continue;
      const Real w = Real(0.125) * p.materials[p.material[q]].mass(p.volume0[q]);  // omega_ap m_p
      m += w;
      mv += w * p.v[q];
      f += corner_force(p, piola, quad, q, int(c.adj[k] & 7));  // eq. 8
    }
    c.m[a] = m;
    c.p[a] = mv;
    c.f[a] = f;
    c.v[a].setZero();
    c.dv[a].setZero();
  });
}

std::size_t domain_point_offsets(const exec::Space& space, const DomainCornerView& c,
                                 std::uint32_t* start) {
  const Real* m = c.m;
  const std::int32_t* enr = c.enriched;
  return exec::parallel_scan<std::uint32_t>(
      space, "domain.point_scan", exec::Index(c.n),
      [=](exec::Index a) { return std::uint32_t(m[a] > 0 && !enr[a]); }, start);
}

void domain_collect_points(const exec::Space& space, const DomainCornerView& c,
                           const std::uint32_t* start, const DomainPointView& out) {
  exec::parallel_for(space, "domain.collect_points", exec::Index(c.n), [&](exec::Index a) {
    if (!(c.m[a] > 0) || c.enriched[a]) return;
    const std::size_t k = start[a];
    out.x[k] = c.x[a];
    out.m[k] = c.m[a];
    out.p[k] = c.p[a];
    out.f[k] = c.f[a];
    if (out.stress) out.stress[k].setZero();
    out.corner[k] = std::int32_t(a);
  });
}

namespace {

// Points are binned by their quadratic stencil base (order-2 keys): a corner's linear stencil
// (floor(x), +1) and a disabled particle's quadratic one (floor(x - 1/2) .. +2) both fit the
// bin's 10^3 block.
using Blk8 = GridBlock<2, 8>;

// Calls fn(w, grad w, block offset) for the nodes of point x's stencil: linear (corners, eq. 3)
// or quadratic B-spline (disabled particles: plain MPM, whose force needs grad w -> 0 where w ->
// 0).
template <int Order, class Blk, class Fn>
inline void for_stencil(const Vec3& x, Real inv_dx, const Vec3i& origin, Fn&& fn) {
  const Stencil<Order> st = Stencil<Order>::at(x, inv_dx);
  const Vec3i l = st.base - origin;
  constexpr int n = Stencil<Order>::kN;
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j)
      for (int k = 0; k < n; ++k)
        fn(st.weight(i, j, k), st.gradient(i, j, k), Blk::at(l[0] + i, l[1] + j, l[2] + k));
}

// Colour-partitioned linear-weight scatter: for each point, lanes(point, w, out[8]) gives the
// values to add at weight w; flush(block node, leaf, offset) adds a node into the grid.
template <class Lanes, class Flush>
void scatter_points(const exec::Space& space, const char* label, const DomainPointView& pts,
                    const MpmGridView& g, Real inv_dx, Lanes&& lanes, Flush&& flush) {
  for (int col = 0; col < 8; ++col) {
    const std::uint32_t c0 = g.colour_start[col], c1 = g.colour_start[col + 1];
    exec::parallel_for(
        space, label, exec::Index(c1 - c0),
        [&](exec::Index ci) {
          const std::uint32_t b = g.colour_bins[c0 + std::uint32_t(ci)];
          Blk8 blk;
          blk.clear();
          const Vec3i origin = g.bin_leaf[b] * kLeafDim;
          for (std::uint32_t q = g.bin_start[b]; q < g.bin_start[b + 1]; ++q) {
            Real v[8];
            lanes(q, v);
            if (pts.corner[q] >= 0) {
              for_stencil<1, Blk8>(pts.x[q], inv_dx, origin, [&](Real w, const Vec3&, int o) {
                for (int ch = 0; ch < 8; ++ch) blk.data[o + ch] += w * v[ch];
              });
              continue;
            }
            // A disabled particle (a plain MPM point) adds its stress force -V0 tau grad w_i.
            const Mat3& S = pts.stress[q];
            for_stencil<2, Blk8>(pts.x[q], inv_dx, origin, [&](Real w, const Vec3& gw, int o) {
              for (int ch = 0; ch < 8; ++ch) blk.data[o + ch] += w * v[ch];
              const Vec3 f = -(S * gw);
              blk.data[o + 5] += f[0], blk.data[o + 6] += f[1], blk.data[o + 7] += f[2];
            });
          }
          blk.for_each_node(g.nbr8[b], flush);
        },
        1);
  }
}

// Per bin: gather the block of 4 lanes from up to two [leaf][512][4] arrays, then per point.
template <class Fn>
void gather_points(const exec::Space& space, const char* label, const DomainPointView& pts,
                   const MpmGridView& g, const Real* a, const Real* b, Real inv_dx, Fn&& fn) {
  exec::parallel_for(space, label, exec::Index(g.nbins), [&](exec::Index bi) {
    const std::size_t bin = std::size_t(bi);
    Blk8 blk;
    blk.for_each_node(g.nbr8[bin], [&](Real* d, std::size_t leaf, int off) {
      const std::size_t n = (leaf * kLeafNodes + std::size_t(off)) * 4;
      for (int ch = 0; ch < 4; ++ch) d[ch] = a[n + std::size_t(ch)];
      for (int ch = 0; ch < 4; ++ch) d[4 + ch] = b ? b[n + std::size_t(ch)] : Real(0);
    });
    const Vec3i origin = g.bin_leaf[bin] * kLeafDim;
    for (std::uint32_t q = g.bin_start[bin]; q < g.bin_start[bin + 1]; ++q) {
      Real acc[8] = {0, 0, 0, 0, 0, 0, 0, 0};
      Mat3 grad = Mat3::Zero();  // sum_i (lanes 1-3)_i grad w_i^T, for disabled particles' points
      auto add = [&](Real w, const Vec3& gw, int o, bool with_grad) {
        const Real* d = blk.data + o;
        for (int ch = 0; ch < 8; ++ch) acc[ch] += w * d[ch];
        if (with_grad) grad += Vec3(d[1], d[2], d[3]) * gw.transpose();
      };
      if (pts.corner[q] >= 0)
        for_stencil<1, Blk8>(pts.x[q], inv_dx, origin,
                             [&](Real w, const Vec3& gw, int o) { add(w, gw, o, false); });
      else
        for_stencil<2, Blk8>(pts.x[q], inv_dx, origin,
                             [&](Real w, const Vec3& gw, int o) { add(w, gw, o, true); });
      fn(q, acc, grad);
    }
  });
}

void clear_leaves(const exec::Space& space, const MpmGridView& g, Real* out) {
  exec::parallel_for(space, "domain.clear", exec::Index(g.nactive), [&](exec::Index i) {
    const std::size_t leaf = std::size_t(g.active_leaves[i]);
    std::fill(out + leaf * kLeafNodes * 4, out + (leaf + 1) * kLeafNodes * 4, Real(0));
  });
}

}  // namespace

void domain_points_to_grid(const exec::Space& space, const DomainPointView& pts,
                           const MpmGridView& g, Real dx) {
  clear_leaves(space, g, g.a);
  clear_leaves(space, g, g.b);
  scatter_points(
      space, "domain.points_to_grid", pts, g, Real(1) / dx,
      [&](std::uint32_t q, Real* v) {
        v[0] = pts.m[q];
        v[1] = pts.p[q][0], v[2] = pts.p[q][1], v[3] = pts.p[q][2];
        v[4] = 0;
        v[5] = pts.f[q][0], v[6] = pts.f[q][1], v[7] = pts.f[q][2];
      },
      [&](Real* s, std::size_t leaf, int off) {
        Real* da = g.a + (leaf * kLeafNodes + std::size_t(off)) * 4;
        Real* db = g.b + (leaf * kLeafNodes + std::size_t(off)) * 4;
        for (int ch = 0; ch < 4; ++ch) da[ch] += s[ch], db[ch] += s[4 + ch];
      });
}

void domain_grid_to_corners(const exec::Space& space, const DomainPointView& pts,
                            const MpmGridView& g, Real dx, const DomainCornerView& c,
                            const DomainParticleView& p, const DomainParams& prm) {
  const Real alpha = prm.flip_alpha, dt = prm.dt, t_end = prm.time + prm.dt;
  gather_points(space, "domain.grid_to_corners", pts, g, g.a, g.b, Real(1) / dx,
                [&](std::uint32_t q, const Real* acc, const Mat3& grad_v) {
                  const Vec3 v(acc[1], acc[2],
                               acc[3]);  // sum omega_i v_i (a = (m, v) after the update)
                  const Vec3 dv(acc[5], acc[6], acc[7]);  // sum omega_i (v_i^{n+1} - v_i^n)
                  if (pts.corner[q] >= 0) {
                    c.v[std::size_t(pts.corner[q])] = v;
                    c.dv[std::size_t(pts.corner[q])] = dv;
                    return;
                  }
                  // A disabled particle: plain PIC/FLIP MPM on linear weights (course report).
                  const std::size_t i = std::size_t(-pts.corner[q] - 1);
                  p.v[i] = (1 - alpha) * v + alpha * (p.v[i] + dv);
                  if (p.C) p.C[i] = grad_v;  // the velocity gradient its viscous stress needs
                  const Mat3 dF = dt * grad_v * p.F[i];  // F += dt grad v F, as g2p
                  if (p.F_lo)
                    add_compensated(p.F[i], p.F_lo[i], dF);
                  else
                    p.F[i] += dF;
                  Vec3 x = p.x[i], lo = p.x_lo ? p.x_lo[i] : Vec3::Zero();
                  add_compensated(x, lo, Vec3(dt * v));
                  for (int k = 0; k < prm.ncolliders; ++k) {  // as collide_particles
                    const Collider& col = prm.colliders[k];
                    const Real phi = col.phi(x, t_end);
                    if (phi >= 0 || col.boundary == BoundaryType::Sticky) continue;
                    add_compensated(x, lo, Vec3(-phi * col.outward_normal(x, t_end)));
                    col.project(x, t_end, p.v[i]);
                  }
                  p.x[i] = x;
                  if (p.x_lo) p.x_lo[i] = lo;
                });
}

std::size_t domain_particle_point_offsets(const exec::Space& space, const DomainParticleView& p,
                                          std::uint32_t* start) {
  const std::int32_t* state = p.state;
  return exec::parallel_scan<std::uint32_t>(
      space, "domain.particle_point_scan", exec::Index(p.n),
      [=](exec::Index i) { return std::uint32_t(state[i] == kDomainDisabled); }, start);
}

void domain_collect_particle_points(const exec::Space& space, const DomainParticleView& p,
                                    const DomainParams& prm, const std::uint32_t* start,
                                    std::size_t base, const DomainPointView& out) {
  exec::parallel_for(space, "domain.collect_particle_points", exec::Index(p.n), [&](exec::Index i) {
    if (p.state[i] != kDomainDisabled) return;
    const std::size_t k = base + start[i];
    const MaterialParams& m = prm.materials[p.material[i]];
    out.x[k] = p.x[i];
    const Real mass = m.mass(p.volume0[i]);
    out.m[k] = mass;
    out.p[k] = mass * p.v[i];
    out.f[k].setZero();
    out.stress[k] = p.volume0[i] * m.kirchhoff(p.F[i], p.C ? p.C[i] : Mat3(Mat3::Zero()),
                                               p.plastic ? p.plastic[i] : Real(0),
                                               p.temperature ? p.temperature[i] : Real(0));
    out.corner[k] = -std::int32_t(i) - 1;
  });
}

std::size_t domain_disable_melted(const exec::Space& space, const DomainParticleView& p,
                                  const MaterialParams* materials) {
  return exec::parallel_reduce(
      space, "domain.disable_melted", exec::Index(p.n), std::size_t(0),
      [&](exec::Index i, std::size_t& acc) {
        if (p.state[i] != kDomainDisabled && p.temperature &&
            materials[p.material[i]].melted(p.temperature[i])) {
          p.state[i] = kDomainDisabled;
          if (p.C) p.C[i].setZero();
        }
        acc += p.state[i] == kDomainDisabled ? 1 : 0;
      },
      [](std::size_t a, std::size_t b) { return a + b; });
}

void domain_update_enriched_corners(const exec::Space& space, const DomainCornerView& c,
                                    const DomainParams& prm) {
  const Real dt = prm.dt;
  const Vec3 g = prm.gravity;
  exec::parallel_for(space, "domain.enriched_update", exec::Index(c.n), [&](exec::Index a) {
    if (!c.enriched[a] || !(c.m[a] > 0)) return;
    const Vec3 v_old = c.p[a] / c.m[a];
    const Vec3 v = v_old + (dt / c.m[a]) * c.f[a] + dt * g;  // eq. 13 on an enriched DOF
    c.v[a] = v;
    c.dv[a] = v - v_old;
  });
}

void domain_collide_corners(const exec::Space& space, const DomainCornerView& c,
                            const DomainParams& prm) {
  if (prm.ncolliders == 0) return;
  const Real t_end = prm.time + prm.dt;
  exec::parallel_for(space, "domain.collide_corners", exec::Index(c.n), [&](exec::Index a) {
    if (!(c.m[a] > 0)) return;
    const Vec3 x_end = c.x[a] + prm.dt * c.v[a];
    Vec3 v = c.v[a];
    for (int k = 0; k < prm.ncolliders; ++k) prm.colliders[k].project(x_end, t_end, v);
    c.dv[a] += v - c.v[a];  // the impulse reaches the particles through both PIC and FLIP parts
    c.v[a] = v;
  });
}

void domain_corners_to_particles(const exec::Space& space, const DomainParticleView& p,
                                 const DomainCornerView& c, const DomainParams& prm) {
  const Real alpha = prm.flip_alpha, dt = prm.dt;
  exec::parallel_for(space, "domain.c2p", exec::Index(p.n), [&](exec::Index i) {
    if (p.state[i] == kDomainDisabled) return;
    Vec3 v_pic = Vec3::Zero(), dv = Vec3::Zero();
    Mat3 gradv = Mat3::Zero();
    for (int s = 0; s < 8; ++s) {
      const std::size_t a = std::size_t(p.corners[8 * i + s]);
      v_pic += c.v[a];
      dv += c.dv[a];
      gradv += c.v[a] * box_corner_gradient(s, p.h[i]).transpose();
    }
    v_pic *= Real(0.125);
    dv *= Real(0.125);
    p.v[i] = (1 - alpha) * v_pic + alpha * (p.v[i] + dv);
    // eq. 7: F^{n+1} = F^n + dt sum_a v_a (grad_X omega_ap)^T
    if (p.F_lo)
      add_compensated(p.F[i], p.F_lo[i], Mat3(dt * gradv));
    else
      p.F[i] += dt * gradv;
  });
}

void domain_advect(const exec::Space& space, const DomainParticleView& p, const DomainCornerView& c,
                   const DomainParams& prm) {
  const Real dt = prm.dt, t_end = prm.time + prm.dt;
  exec::parallel_for(space, "domain.advect_corners", exec::Index(c.n), [&](exec::Index a) {
    if (!(c.m[a] > 0)) return;
    Vec3 x = c.x[a] + dt * c.v[a];
    for (int k = 0; k < prm.ncolliders; ++k) {
      const Collider& col = prm.colliders[k];
      if (col.boundary == BoundaryType::Sticky) continue;  // a grip holds what it holds
      const Real phi = col.phi(x, t_end);
      if (phi < 0) x -= phi * col.outward_normal(x, t_end);  // projected to the surface (Sec. 7)
    }
    c.x[a] = x;
  });
  exec::parallel_for(space, "domain.advect_particles", exec::Index(p.n), [&](exec::Index i) {
    if (p.state[i] == kDomainDisabled) return;
    Vec3 x = Vec3::Zero();
    for (int s = 0; s < 8; ++s) x += c.x[std::size_t(p.corners[8 * i + s])];
    p.x[i] = Real(0.125) * x;
    if (p.x_lo) p.x_lo[i].setZero();
  });
}

void domain_corner_increments(const exec::Space& space, const DomainPointView& pts,
                              const MpmGridView& g, Real dx, const Real* du_grid,
                              const DomainCornerView& c, const std::int32_t* dof,
                              const Real* du_corner, Vec3* du_c) {
  exec::parallel_for(space, "domain.du_enriched", exec::Index(c.n), [&](exec::Index a) {
    const std::int32_t d = dof[a];
    du_c[a] = d >= 0 ? Vec3(du_corner[4 * std::size_t(d)], du_corner[4 * std::size_t(d) + 1],
                            du_corner[4 * std::size_t(d) + 2])
                     : Vec3::Zero();
  });
  gather_points(space, "domain.du_grid", pts, g, du_grid, nullptr, Real(1) / dx,
                [&](std::uint32_t q, const Real* acc, const Mat3&) {
                  // disabled particles' points are not in the Hessian (their stress is explicit)
                  if (pts.corner[q] >= 0) du_c[pts.corner[q]] = Vec3(acc[0], acc[1], acc[2]);
                });
}

void domain_corner_hessian_forces(const exec::Space& space, const DomainParticleView& p,
                                  const DomainCornerView& c, const DomainHessian* hess,
                                  const DomainQuadrature& quad, const Vec3* du_c, Mat3* scratch,
                                  Vec3* df_c) {
  exec::parallel_for(space, "domain.dP", exec::Index(p.n), [&](exec::Index i) {
    if (p.state[i] == kDomainDisabled) return;
    const std::int32_t* cn = p.corners + 8 * i;
    const std::int32_t e = quad.index ? quad.index[i] : -1;
    if (e >= 0) {  // V0/8 dP_g at each Gauss point
      for (int g = 0; g < 8; ++g) {
        Mat3 dF = Mat3::Zero();
        for (int a = 0; a < 8; ++a)
          dF += du_c[std::size_t(cn[a])] * box_gauss_gradient(a, g, p.h[i]).transpose();
        quad.scratch[8 * std::size_t(e) + std::size_t(g)] =
            quad.hess[8 * std::size_t(e) + std::size_t(g)].stress_differential(dF);
      }
      return;
    }
    Mat3 dF = Mat3::Zero();
    for (int s = 0; s < 8; ++s)
      dF += du_c[std::size_t(cn[s])] * box_corner_gradient(s, p.h[i]).transpose();
    scratch[i] = hess[i].stress_differential(dF);  // V0 dP (eqs. 15-16)
  });
  exec::parallel_for(space, "domain.df", exec::Index(c.n), [&](exec::Index a) {
    Vec3 f = Vec3::Zero();
    for (std::uint32_t k = c.adj_start[a]; k < c.adj_start[a + 1]; ++k) {
      const std::size_t q = c.adj[k] >> 3;
      if (p.state[q] == kDomainDisabled) continue;
      for_each_point(p, quad, q, int(c.adj[k] & 7), [&](const Vec3& grad, std::ptrdiff_t e) {
        f += (e < 0 ? scratch[q] : quad.scratch[e]) * grad;  // eq. 14
      });
    }
    df_c[a] = f;
  });
}

namespace {
// Corner values -> DOFs: unenriched corners through the points with weight omega_i (or omega_i^2
// for a diagonal), enriched corners onto their own DOF.
void corner_values_to_dofs(const exec::Space& space, const DomainPointView& pts,
                           const MpmGridView& g, Real dx, const DomainCornerView& c,
                           const std::int32_t* dof, const Vec3* val, Real scale, bool squared,
                           Real* out_grid, Real* out_corner) {
  if (pts.n > 0) {
    for (int col = 0; col < 8; ++col) {
      const std::uint32_t c0 = g.colour_start[col], c1 = g.colour_start[col + 1];
      exec::parallel_for(
          space, "domain.values_to_grid", exec::Index(c1 - c0),
          [&](exec::Index ci) {
            const std::uint32_t b = g.colour_bins[c0 + std::uint32_t(ci)];
            GridBlock<2, 4> blk;
            blk.clear();
            const Vec3i origin = g.bin_leaf[b] * kLeafDim;
            const Real inv_dx = Real(1) / dx;
            for (std::uint32_t q = g.bin_start[b]; q < g.bin_start[b + 1]; ++q) {
              const Stencil<1> st = Stencil<1>::at(pts.x[q], inv_dx);
              const Vec3i l = st.base - origin;
              if (pts.corner[q] < 0) continue;  // a disabled particle's point
              const Vec3 f = scale * val[pts.corner[q]];
              for (int i = 0; i < 2; ++i)
                for (int j = 0; j < 2; ++j)
                  for (int k = 0; k < 2; ++k) {
                    Real w = st.weight(i, j, k);
                    if (squared) w *= w;
                    Real* d = blk.data + GridBlock<2, 4>::at(l[0] + i, l[1] + j, l[2] + k);
                    d[0] += w * f[0], d[1] += w * f[1], d[2] += w * f[2];
                  }
            }
            blk.for_each_node(g.nbr8[b], [&](Real* s, std::size_t leaf, int off) {
              Real* d = out_grid + (leaf * kLeafNodes + std::size_t(off)) * 4;
              d[0] += s[0], d[1] += s[1], d[2] += s[2];
            });
          },
          1);
    }
  }
  exec::parallel_for(space, "domain.values_to_corners", exec::Index(c.n), [&](exec::Index a) {
    const std::int32_t d = dof[a];
    if (d < 0) return;
    Real* o = out_corner + 4 * std::size_t(d);
    const Vec3 f = scale * val[a];
    o[0] += f[0], o[1] += f[1], o[2] += f[2];
  });
}
}  // namespace

void domain_forces_to_dofs(const exec::Space& space, const DomainPointView& pts,
                           const MpmGridView& g, Real dx, const DomainCornerView& c,
                           const std::int32_t* dof, const Vec3* df_c, Real scale, Real* out_grid,
                           Real* out_corner) {
  corner_values_to_dofs(space, pts, g, dx, c, dof, df_c, scale, false, out_grid, out_corner);
}
void domain_diagonal_to_dofs(const exec::Space& space, const DomainPointView& pts,
                             const MpmGridView& g, Real dx, const DomainCornerView& c,
                             const std::int32_t* dof, const Vec3* d_c, Real scale, Real* diag_grid,
                             Real* diag_corner) {
  corner_values_to_dofs(space, pts, g, dx, c, dof, d_c, scale, true, diag_grid, diag_corner);
}

void domain_corner_hessian_diagonal(const exec::Space& space, const DomainParticleView& p,
                                    const DomainCornerView& c, const DomainHessian* hess,
                                    const DomainQuadrature& quad, Vec3* d_c) {
  // dF = e_k gr^T: (dF : dP/dF : dF) = rank-one quadratic of a = U^T e_k, b = V^T gr (eqs. 18-19)
  auto add = [](const DomainHessian& h, const Vec3& gr, Vec3& d) {
    const Vec3 b = h.V.transpose() * gr;
    for (int ax = 0; ax < 3; ++ax)
      d[ax] += h.V0 * h.h.rank_one_quadratic(h.U.row(ax).transpose(), b);
  };
  exec::parallel_for(space, "domain.diag", exec::Index(c.n), [&](exec::Index a) {
    Vec3 d = Vec3::Zero();
    for (std::uint32_t k = c.adj_start[a]; k < c.adj_start[a + 1]; ++k) {
      const std::size_t q = c.adj[k] >> 3;
      if (p.state[q] == kDomainDisabled) continue;
      for_each_point(p, quad, q, int(c.adj[k] & 7), [&](const Vec3& grad, std::ptrdiff_t e) {
        add(e < 0 ? hess[q] : quad.hess[e], grad, d);
      });
    }
    d_c[a] = d;
  });
}

}  // namespace amalgam
