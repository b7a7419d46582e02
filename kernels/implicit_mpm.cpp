#include "kernels/implicit_mpm.hpp"

#include "core/math/bspline.hpp"
#include "core/math/svd3.hpp"
#include "kernels/grid_block.hpp"

namespace amalgam {

ParticleHessian particle_hessian(const MaterialParams& m, const Mat3& F, Real plastic,
                                 Real temperature, Real V0, bool psd) {
  const Svd3<Real> d = svd3(F);
  Vec3 p;
  Mat3 H;
  m.sigma_derivatives(d.sigma, plastic, temperature, p, H);
  ParticleHessian ph;
  ph.U = d.U;
  ph.sigma = d.sigma;
  ph.h = SvdFrameHessian<Real>::from(d.sigma, p, H);
  if (psd) ph.h.make_psd();
  ph.V0 = V0;
  ph.tau = p.cwiseProduct(d.sigma);
  return ph;
}

namespace {

// The transfer's g_ip in separable form: g_ip = (d0_i w1_j w2_k, w0_i d1_j w2_k, w0_i w1_j d2_k)
// with d = d w / dx (B-spline gradient), or for MLS d_a[i] = D^{-1} (i - fx_a) dx w_a[i], so that
// g_ip = w_ip D_p^{-1} (x_i - x_p).
template <int Order>
inline Stencil<Order> gradient_stencil(const Vec3& x, Real inv_dx, bool mls) {
  Stencil<Order> st = Stencil<Order>::at(x, inv_dx);
  if (mls) {
    const Real s = BSpline<Order>::kDinvScale * inv_dx;
    for (int a = 0; a < 3; ++a)
      for (int k = 0; k < Stencil<Order>::kN; ++k)
        st.dw[a][k] = s * (Real(k) - st.fx[a]) * st.w[a][k];
  }
  return st;
}

// sum_i u_i g_ip^T from a block of 4-lane node vectors (hierarchical sums over k, j, i).
// Since sum_i g_ip = 0 (partition of unity, or MLS's linear reproduction), the sum is taken of
// u_i - u_c with u_c the stencil's centre node: mathematically the same, but a uniform u (a
// rigid translation, e.g. free fall) gives exactly 0 instead of float round-off times
// |u| / dx, which dt^2 times the stiffness would lift to the solver's tolerance (measured:
// a falling stiff armadillo took 25 CG iterations per substep fighting that noise).
template <int Order>
inline Mat3 gather_gradient(const GridBlock<Order, 4>& blk, const Vec3i& l,
                            const Stencil<Order>& st) {
  constexpr int N = Stencil<Order>::kN;
  const Real* centre = blk.data + GridBlock<Order, 4>::at(l[0] + 1, l[1] + 1, l[2] + 1);
  const Real uc[4] = {centre[0], centre[1], centre[2], centre[3]};
  Real D0[4] = {}, D1[4] = {}, D2[4] = {};
  for (int i = 0; i < N; ++i) {
    Real Ti[4] = {}, Tdy[4] = {}, Tdz[4] = {};
    for (int j = 0; j < N; ++j) {
      Real U[4] = {}, Ud[4] = {};
      const Real* row = blk.data + GridBlock<Order, 4>::at(l[0] + i, l[1] + j, l[2]);
      for (int k = 0; k < N; ++k)
        for (int c = 0; c < 4; ++c) {
          const Real u = row[k * 4 + c] - uc[c];
          U[c] += st.w[2][k] * u;
          Ud[c] += st.dw[2][k] * u;
        }
      const Real wy = st.w[1][j], dwy = st.dw[1][j];
      for (int c = 0; c < 4; ++c) {
        Ti[c] += wy * U[c];
        Tdy[c] += dwy * U[c];
        Tdz[c] += wy * Ud[c];
      }
    }
    const Real wx = st.w[0][i], dwx = st.dw[0][i];
    for (int c = 0; c < 4; ++c) {
      D0[c] += dwx * Ti[c];
      D1[c] += wx * Tdy[c];
      D2[c] += wx * Tdz[c];
    }
  }
  Mat3 grad;
  for (int c = 0; c < 3; ++c) grad(c, 0) = D0[c], grad(c, 1) = D1[c], grad(c, 2) = D2[c];
  return grad;
}

// block_i += G g_ip for the particle's stencil nodes.
template <int Order>
inline void scatter_gradient(GridBlock<Order, 4>& blk, const Vec3i& l, const Stencil<Order>& st,
                             const Mat3& G) {
  constexpr int N = Stencil<Order>::kN;
  for (int i = 0; i < N; ++i)
    for (int j = 0; j < N; ++j) {
      const Real wx = st.w[0][i], wy = st.w[1][j];
      const Vec3 a = G.col(0) * (st.dw[0][i] * wy) + G.col(1) * (wx * st.dw[1][j]);
      const Vec3 b = G.col(2) * (wx * wy);
      const Real g0[4] = {a[0], a[1], a[2], 0}, g1[4] = {b[0], b[1], b[2], 0};
      Real* row = blk.data + GridBlock<Order, 4>::at(l[0] + i, l[1] + j, l[2]);
      for (int k = 0; k < N; ++k)
        for (int c = 0; c < 4; ++c) row[k * 4 + c] += st.w[2][k] * g0[c] + st.dw[2][k] * g1[c];
    }
}

// For each colour, each bin: optionally gather `in` from its 8 leaves, compute a G per particle,
// scatter G g_ip into a private block, add the block into `out`.
// L (A-ULMPM Lagrangian mode, p.X_ref set): the stencil sits at the reference position X^s and
// g^s_ip is the reference-configuration gradient. F(u) = (F^{sn} + sum_j u_j g^s_jp^T) F^{0s}
// = (I + sum_j u_j g~_jp^T) F with g~ = (F^{sn})^{-T} g^s (eqs. 24-26), so the Eulerian formulas
// hold with g~: the gathered gradient is right-multiplied by (F^{sn})^{-1} and the scattered G by
// (F^{sn})^{-T} (the force then is -V0 P (F^{0s})^T g^s, eq. 20).
template <int Order, bool L, class PerParticle>
void colour_gather_scatter_impl(const exec::Space& space, const char* label,
                                const MpmParticleView& p, const MpmGridView& g,
                                const ImplicitKernelParams& prm, const Real* in, Real* out,
                                PerParticle per_particle) {
  using Blk = GridBlock<Order, 4>;
  const Real inv_dx = Real(1) / prm.dx;
  const bool mls = prm.transfer == Transfer::Mls;
  for (int c = 0; c < 8; ++c) {
    const std::uint32_t c0 = g.colour_start[c], c1 = g.colour_start[c + 1];
    exec::parallel_for(
        space, label, exec::Index(c1 - c0),
        [&](exec::Index ci) {
          const std::uint32_t b = g.colour_bins[c0 + std::uint32_t(ci)];
          Blk src, acc;
          if (in) src.gather4(g.nbr8[b], in);
          acc.clear();
          const Vec3i origin = g.bin_leaf[b] * kLeafDim;
          for (std::uint32_t q = g.bin_start[b]; q < g.bin_start[b + 1]; ++q) {
            if constexpr (L) {
              const Stencil<Order> st = gradient_stencil<Order>(p.X_ref[q], inv_dx, mls);
              const Vec3i l = st.base - origin;
              const Mat3 Fs_inv = p.F_s[q].inverse();
              const Mat3 grad =
                  in ? Mat3(gather_gradient<Order>(src, l, st) * Fs_inv) : Mat3::Zero();
              scatter_gradient<Order>(acc, l, st, per_particle(q, grad) * Fs_inv.transpose());
            } else {
              const Stencil<Order> st = gradient_stencil<Order>(p.x[q], inv_dx, mls);
              const Vec3i l = st.base - origin;
              const Mat3 grad = in ? gather_gradient<Order>(src, l, st) : Mat3::Zero();
              scatter_gradient<Order>(acc, l, st, per_particle(q, grad));
            }
          }
          acc.flush_add4(g.nbr8[b], out);
        },
        1);
  }
}

template <int Order, class PerParticle>
void colour_gather_scatter(const exec::Space& space, const char* label, const MpmParticleView& p,
                           const MpmGridView& g, const ImplicitKernelParams& prm, const Real* in,
                           Real* out, PerParticle per_particle) {
  if (p.X_ref)
    colour_gather_scatter_impl<Order, true>(space, label, p, g, prm, in, out, per_particle);
  else
    colour_gather_scatter_impl<Order, false>(space, label, p, g, prm, in, out, per_particle);
}

template <int Order, bool L>
void hessian_diagonal_impl(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                           const ImplicitKernelParams& prm, const ParticleHessian* hess, Real scale,
                           Real* diag) {
  using Blk = GridBlock<Order, 4>;
  constexpr int N = Stencil<Order>::kN;
  const Real inv_dx = Real(1) / prm.dx;
  const bool mls = prm.transfer == Transfer::Mls;
  for (int c = 0; c < 8; ++c) {
    const std::uint32_t c0 = g.colour_start[c], c1 = g.colour_start[c + 1];
    exec::parallel_for(
        space, "implicit.hessian_diagonal", exec::Index(c1 - c0),
        [&](exec::Index ci) {
          const std::uint32_t b = g.colour_bins[c0 + std::uint32_t(ci)];
          Blk acc;
          acc.clear();
          const Vec3i origin = g.bin_leaf[b] * kLeafDim;
          for (std::uint32_t q = g.bin_start[b]; q < g.bin_start[b + 1]; ++q) {
            const ParticleHessian& ph = hess[q];
            const Stencil<Order> st = gradient_stencil<Order>(L ? p.X_ref[q] : p.x[q], inv_dx, mls);
            const Vec3i l = st.base - origin;
            // diag_c = M : frame(M) for M = u_c b^T, u_c = row c of U, b = S U^T g (eq. 18 in the
            // frame): a quadratic form in b, Q_c(i,i) = u_i^2 H_ii + sum_{j != i} c1_ij u_j^2,
            // Q_c(i,j) = u_i u_j (H_ij + c2_ij); so diag_c = g^T K_c g with K_c = U S Q_c S U^T,
            // three symmetric 3x3 matrices per particle instead of a frame product per node.
            Mat3 K[3];
            for (int c = 0; c < 3; ++c) {
              const Vec3 u = ph.U.row(c).transpose();
              const Vec3 c1 = ph.h.c1, c2 = ph.h.c2;  // pairs (0,1), (0,2), (1,2)
              Mat3 Q;
              Q(0, 0) = u[0] * u[0] * ph.h.H(0, 0) + c1[0] * u[1] * u[1] + c1[1] * u[2] * u[2];
              Q(1, 1) = u[1] * u[1] * ph.h.H(1, 1) + c1[0] * u[0] * u[0] + c1[2] * u[2] * u[2];
              Q(2, 2) = u[2] * u[2] * ph.h.H(2, 2) + c1[1] * u[0] * u[0] + c1[2] * u[1] * u[1];
              Q(0, 1) = Q(1, 0) = u[0] * u[1] * (ph.h.H(0, 1) + c2[0]);
              Q(0, 2) = Q(2, 0) = u[0] * u[2] * (ph.h.H(0, 2) + c2[1]);
              Q(1, 2) = Q(2, 1) = u[1] * u[2] * (ph.h.H(1, 2) + c2[2]);
              const Mat3 US = ph.U * ph.sigma.asDiagonal();
              K[c] = (scale * ph.V0) * (US * Q * US.transpose());
            }
            if constexpr (
                L) {  // g~ = (F^{sn})^{-T} g^s: g~^T K g~ = g^s^T (F^{sn})^{-1} K (F^{sn})^{-T} g^s
              const Mat3 Fs_inv = p.F_s[q].inverse();
              for (int c = 0; c < 3; ++c) K[c] = Fs_inv * K[c] * Fs_inv.transpose();
            }
            for (int i = 0; i < N; ++i)
              for (int j = 0; j < N; ++j)
                for (int k = 0; k < N; ++k) {
                  const Vec3 gv = st.gradient(i, j, k);
                  Real* node = acc.data + Blk::at(l[0] + i, l[1] + j, l[2] + k);
                  for (int c = 0; c < 3; ++c) node[c] += gv.dot(K[c] * gv);
                }
          }
          acc.flush_add4(g.nbr8[b], diag);
        },
        1);
  }
}

template <int Order>
void dispatch_action(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                     const ImplicitKernelParams& prm, const ParticleHessian* hess, const Real* du,
                     Real scale, Real* out) {
  colour_gather_scatter<Order>(space, "implicit.hessian_action", p, g, prm, du, out,
                               [hess, scale](std::uint32_t q, const Mat3& grad) -> Mat3 {
                                 return scale * particle_stress_differential(hess[q], grad);
                               });
}

template <int Order>
void dispatch_forces(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                     const ImplicitKernelParams& prm, const Real* u, Real* f) {
  const MaterialParams* mats = prm.materials;
  colour_gather_scatter<Order>(space, "implicit.elastic_forces", p, g, prm, u, f,
                               [&p, mats](std::uint32_t q, const Mat3& grad) -> Mat3 {
                                 const Mat3 Fu = (Mat3::Identity() + grad) * p.F[q];
                                 const Svd3<Real> d = svd3(Fu);
                                 Vec3 ps;
                                 Mat3 H;
                                 mats[p.material[q]].sigma_derivatives(
                                     d.sigma, p.plastic ? p.plastic[q] : Real(0),
                                     p.temperature ? p.temperature[q] : Real(0), ps, H);
                                 const Mat3 P = d.U * ps.asDiagonal() * d.V.transpose();
                                 return -p.volume0[q] * (P * p.F[q].transpose());
                               });
}

template <int Order>
void dispatch_cached_forces(const exec::Space& space, const MpmParticleView& p,
                            const MpmGridView& g, const ImplicitKernelParams& prm,
                            const ParticleHessian* hess, Real* f) {
  colour_gather_scatter<Order>(space, "implicit.cached_forces", p, g, prm, nullptr, f,
                               [hess](std::uint32_t q, const Mat3&) -> Mat3 {
                                 const ParticleHessian& ph = hess[q];
                                 return -ph.V0 * (ph.U * ph.tau.asDiagonal() * ph.U.transpose());
                               });
}

}  // namespace

void mpm_cached_elastic_forces(const exec::Space& space, const MpmParticleView& p,
                               const MpmGridView& g, const ImplicitKernelParams& prm,
                               const ParticleHessian* hess, Real* f) {
  if (prm.order == 3)
    dispatch_cached_forces<3>(space, p, g, prm, hess, f);
  else
    dispatch_cached_forces<2>(space, p, g, prm, hess, f);
}

void prepare_particle_hessians(const exec::Space& space, const MpmParticleView& p,
                               const ImplicitKernelParams& prm, bool psd, ParticleHessian* out) {
  const MaterialParams* mats = prm.materials;
  exec::parallel_for(space, "implicit.prepare_hessians", exec::Index(p.n), [&](exec::Index q) {
    out[q] = particle_hessian(mats[p.material[q]], p.F[q], p.plastic ? p.plastic[q] : Real(0),
                              p.temperature ? p.temperature[q] : Real(0), p.volume0[q], psd);
  });
}

void mpm_hessian_action(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                        const ImplicitKernelParams& prm, const ParticleHessian* hess,
                        const Real* du, Real scale, Real* out) {
  if (prm.order == 3)
    dispatch_action<3>(space, p, g, prm, hess, du, scale, out);
  else
    dispatch_action<2>(space, p, g, prm, hess, du, scale, out);
}

void mpm_hessian_diagonal(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                          const ImplicitKernelParams& prm, const ParticleHessian* hess, Real scale,
                          Real* diag) {
  if (p.X_ref) {
    if (prm.order == 3)
      hessian_diagonal_impl<3, true>(space, p, g, prm, hess, scale, diag);
    else
      hessian_diagonal_impl<2, true>(space, p, g, prm, hess, scale, diag);
  } else {
    if (prm.order == 3)
      hessian_diagonal_impl<3, false>(space, p, g, prm, hess, scale, diag);
    else
      hessian_diagonal_impl<2, false>(space, p, g, prm, hess, scale, diag);
  }
}

void mpm_elastic_forces(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                        const ImplicitKernelParams& prm, const Real* u, Real* f) {
  if (prm.order == 3)
    dispatch_forces<3>(space, p, g, prm, u, f);
  else
    dispatch_forces<2>(space, p, g, prm, u, f);
}

}  // namespace amalgam

namespace amalgam {

void grid_velocities_to_dofs(const exec::Space& space, const MpmGridView& g, Real* mass, Real* v) {
  exec::parallel_for(space, "implicit.grid_to_dofs", exec::Index(g.nactive), [&](exec::Index li) {
    const std::size_t d0 = std::size_t(g.active_leaves[li]) * kLeafNodes;
    const Real* a = g.a + d0 * 4;
    for (std::size_t n = 0; n < std::size_t(kLeafNodes); ++n) {
      mass[d0 + n] = a[n * 4];
      Real* vd = v + (d0 + n) * 4;
      vd[0] = a[n * 4 + 1], vd[1] = a[n * 4 + 2], vd[2] = a[n * 4 + 3], vd[3] = 0;
    }
  });
}

void initial_guess_from_force(const exec::Space& space, const MpmGridView& g, const Real* mass,
                              const Real* f, Real dt, Real* v) {
  exec::parallel_for(space, "implicit.initial_guess", exec::Index(g.nactive), [&](exec::Index li) {
    const std::size_t d0 = std::size_t(g.active_leaves[li]) * kLeafNodes;
    for (std::size_t d = d0; d < d0 + std::size_t(kLeafNodes); ++d) {
      if (mass[d] <= 0) continue;
      const Real s = dt / mass[d];
      for (int c = 0; c < 3; ++c) v[d * 4 + c] -= s * f[d * 4 + c];
    }
  });
}

void dofs_to_grid_velocities(const exec::Space& space, const MpmGridView& g, const Real* v) {
  exec::parallel_for(space, "implicit.dofs_to_grid", exec::Index(g.nactive), [&](exec::Index li) {
    const std::size_t d0 = std::size_t(g.active_leaves[li]) * kLeafNodes;
    Real* a = g.a + d0 * 4;
    Real* b = g.b ? g.b + d0 * 4 : nullptr;
    for (std::size_t n = 0; n < std::size_t(kLeafNodes); ++n) {
      if (a[n * 4] <= 0) continue;
      const Real* vd = v + (d0 + n) * 4;
      for (int c = 0; c < 3; ++c) {
        if (b) b[n * 4 + 1 + c] += vd[c] - a[n * 4 + 1 + c];
        a[n * 4 + 1 + c] = vd[c];
      }
    }
  });
}

}  // namespace amalgam
