#include "solvers/implicit_system.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

#include "core/errors.hpp"

namespace amalgam {

const char* krylov_name(KrylovMethod m) {
  return m == KrylovMethod::Cg ? "cg" : "minres";
}

namespace {
constexpr std::uint32_t kBlock = 512;
}

void ImplicitSystem::begin(std::size_t grid_dofs, const std::vector<std::int32_t>& grid_leaves) {
  grid_dofs_ = grid_dofs;
  ndof_ = grid_dofs;
  blocks_.clear();
  for (const std::int32_t leaf : grid_leaves)
    blocks_.push_back({std::uint64_t(leaf) * kBlock, kBlock});
  terms_.clear();
}

std::size_t ImplicitSystem::add_dof_set(std::size_t count) {
  const std::size_t first = ndof_;
  for (std::size_t b = 0; b < count; b += kBlock)
    blocks_.push_back(
        {std::uint64_t(first + b), std::uint32_t(std::min<std::size_t>(kBlock, count - b))});
  ndof_ += count;
  return first;
}

void ImplicitSystem::finalize() {
  auto zero = [this](std::vector<Real>& v, std::size_t lanes) { v.assign(ndof_ * lanes, Real(0)); };
  zero(mass_, 1);
  zero(vstar_, 4);
  zero(x_, 4);
  zero(inv_diag_, 4);
  con_dof_.clear();
  con_P_.clear();
  con_val_.clear();
  con_index_.assign(ndof_, -1);
  preconditioner_dt_ = -1;
}

void ImplicitSystem::fix(std::size_t dof, const Vec3& v) {
  preconditioner_dt_ = -1;
  std::int32_t& c = con_index_[dof];
  if (c < 0) {
    c = std::int32_t(con_dof_.size());
    con_dof_.push_back(dof);
    con_P_.push_back(Mat3::Zero());
    con_val_.push_back(v);
    return;
  }
  con_P_[size_t(c)].setZero();
  con_val_[size_t(c)] = v;
}

void ImplicitSystem::constrain_normal(std::size_t dof, const Vec3& n, Real vn) {
  preconditioner_dt_ = -1;
  std::int32_t& c = con_index_[dof];
  if (c < 0) {
    c = std::int32_t(con_dof_.size());
    con_dof_.push_back(dof);
    con_P_.push_back(Mat3::Identity() - n * n.transpose());
    con_val_.push_back(vn * n);
    return;
  }
  // Combine: the new normal's free part (Gram-Schmidt against the directions already fixed).
  Mat3& P = con_P_[size_t(c)];
  const Vec3 m = P * n;
  const Real len = m.norm();
  if (len < Real(1e-3)) return;  // (nearly) parallel to a fixed direction: keep the first
  const Vec3 e = m / len;
  // Value along e: n . v = vn with v = fixed part + s e  =>  s = (vn - n . fixed) / (n . e).
  const Real s = (vn - n.dot(con_val_[size_t(c)])) / n.dot(e);
  con_val_[size_t(c)] += s * e;
  P -= e * e.transpose();
}

void ImplicitSystem::project(const exec::Space& space, Real* v) const {
  const std::uint64_t* dof = con_dof_.data();
  const Mat3* P = con_P_.data();
  exec::parallel_for(space, "implicit.project", exec::Index(con_dof_.size()), [=](exec::Index c) {
    Real* d = v + dof[c] * 4;
    const Vec3 p = P[c] * Vec3(d[0], d[1], d[2]);
    d[0] = p[0], d[1] = p[1], d[2] = p[2];
  });
}

double ImplicitSystem::dot(const exec::Space& space, const Real* a, const Real* b) const {
  const Block* blk = blocks_.data();
  return exec::parallel_reduce(
      space, "implicit.dot", exec::Index(blocks_.size()), 0.0,
      [=](exec::Index i, double& acc) {
        const Real* x = a + blk[i].first * 4;
        const Real* y = b + blk[i].first * 4;
        double s = 0;
        for (std::uint32_t k = 0; k < blk[i].count * 4; ++k) s += double(x[k]) * double(y[k]);
        acc += s;
      },
      [](double x, double y) { return x + y; });
}

ImplicitSystem::Dots ImplicitSystem::dots(const exec::Space& space, const Real* r,
                                          const Real* z) const {
  const Block* blk = blocks_.data();
  const Real* m = mass_.data();
  return exec::parallel_reduce(
      space, "implicit.dot", exec::Index(blocks_.size()), Dots{},
      [=](exec::Index i, Dots& acc) {
        double rz = 0, mzz = 0;
        for (std::uint64_t d = blk[i].first; d < blk[i].first + blk[i].count; ++d) {
          double zz = 0;
          for (int c = 0; c < 3; ++c) {
            rz += double(r[d * 4 + c]) * double(z[d * 4 + c]);
            zz += double(z[d * 4 + c]) * double(z[d * 4 + c]);
          }
          mzz += double(m[d]) * zz;
        }
        acc.rz += rz;
        acc.mzz += mzz;
      },
      [](Dots a, const Dots& b) {
        a.rz += b.rz;
        a.mzz += b.mzz;
        return a;
      });
}

double ImplicitSystem::mass_norm2(const exec::Space& space, const Real* v) const {
  const Block* blk = blocks_.data();
  const Real* m = mass_.data();
  return exec::parallel_reduce(
      space, "implicit.dot", exec::Index(blocks_.size()), 0.0,
      [=](exec::Index i, double& acc) {
        double s = 0;
        for (std::uint64_t d = blk[i].first; d < blk[i].first + blk[i].count; ++d)
          if (m[d] > 0)
            s += double(m[d]) * (double(v[d * 4]) * double(v[d * 4]) +
                                 double(v[d * 4 + 1]) * double(v[d * 4 + 1]) +
                                 double(v[d * 4 + 2]) * double(v[d * 4 + 2]));
        acc += s;
      },
      [](double a, double b) { return a + b; });
}

void ImplicitSystem::apply(const exec::Space& space, Real dt, const Real* v, Real* out) const {
  const Block* blk = blocks_.data();
  const Real* m = mass_.data();
  exec::parallel_for(space, "implicit.apply_mass", exec::Index(blocks_.size()), [=](exec::Index i) {
    for (std::uint64_t d = blk[i].first; d < blk[i].first + blk[i].count; ++d)
      for (int c = 0; c < 4; ++c) out[d * 4 + c] = m[d] * v[d * 4 + c];
  });
  for (const ImplicitTerm* t : terms_) t->add_hessian_action(space, v, dt * dt, out);
}

void ImplicitSystem::prepare(const exec::Space& space, Real dt) {
  if (preconditioner_dt_ != dt) build_preconditioner(space, dt);
  preconditioner_dt_ = dt;
}

void ImplicitSystem::build_preconditioner(const exec::Space& space, Real dt) {
  Real* diag = inv_diag_.data();
  std::fill(inv_diag_.begin(), inv_diag_.end(), Real(0));
  for (const ImplicitTerm* t : terms_) t->add_hessian_diagonal(space, dt * dt, diag);
  const Block* blk = blocks_.data();
  const Real* m = mass_.data();
  const std::int32_t* con = con_index_.data();
  const Mat3* P = con_P_.data();
  // D = m + dt^2 max(diag H, 0) (eq. 17; clamped so MINRES's preconditioner stays definite). A
  // massless or fully fixed DOF gets 0: its residual never enters the search directions.
  exec::parallel_for(space, "implicit.preconditioner", exec::Index(blocks_.size()),
                     [=](exec::Index i) {
                       for (std::uint64_t d = blk[i].first; d < blk[i].first + blk[i].count; ++d) {
                         const bool fixed = m[d] <= 0 || (con[d] >= 0 && P[con[d]].isZero());
                         for (int c = 0; c < 4; ++c) {
                           const Real D = m[d] + std::max(diag[d * 4 + c], Real(0));
                           diag[d * 4 + c] = (fixed || c == 3) ? Real(0) : Real(1) / D;
                         }
                       }
                     });
}

void ImplicitSystem::apply_preconditioner(const exec::Space& space, const Real* r, Real* z) const {
  const Block* blk = blocks_.data();
  const Real* inv = inv_diag_.data();
  exec::parallel_for(space, "implicit.jacobi", exec::Index(blocks_.size()), [=](exec::Index i) {
    const std::uint64_t b = blk[i].first * 4, e = b + std::uint64_t(blk[i].count) * 4;
    for (std::uint64_t k = b; k < e; ++k) z[k] = inv[k] * r[k];
  });
  project(space, z);
}

SolveStats ImplicitSystem::solve(const exec::Space& space, Real dt, const ImplicitSettings& s) {
  const std::size_t n4 = ndof_ * 4;
  for (auto* v : {&r_, &z_, &p_, &q_})
    if (v->size() != n4) v->assign(n4, Real(0));
  prepare(space, dt);
  const Block* blk = blocks_.data();
  const Real* m = mass_.data();
  Real* x = x_.data();
  Real* r = r_.data();
  Real* z = z_.data();
  Real* p = p_.data();
  Real* q = q_.data();
  const Real* vstar = vstar_.data();
  const std::int32_t* con = con_index_.data();
  const Mat3* P = con_P_.data();
  const Vec3* val = con_val_.data();
  // x0: the guess with its constrained part replaced by the prescribed values; massless DOFs 0.
  exec::parallel_for(space, "implicit.initial_guess", exec::Index(blocks_.size()),
                     [=](exec::Index i) {
                       for (std::uint64_t d = blk[i].first; d < blk[i].first + blk[i].count; ++d) {
                         Real* xd = x + d * 4;
                         if (m[d] <= 0) {
                           xd[0] = xd[1] = xd[2] = xd[3] = 0;
                           continue;
                         }
                         if (con[d] >= 0) {
                           const Vec3 v = P[con[d]] * Vec3(xd[0], xd[1], xd[2]) + val[con[d]];
                           xd[0] = v[0], xd[1] = v[1], xd[2] = v[2];
                         }
                         xd[3] = 0;
                       }
                     });
  // r = P (M v* - A x0); the right-hand side's norm for the relative residual: b = P M v*.
  apply(space, dt, x, q);
  exec::parallel_for(space, "implicit.residual", exec::Index(blocks_.size()), [=](exec::Index i) {
    for (std::uint64_t d = blk[i].first; d < blk[i].first + blk[i].count; ++d)
      for (int c = 0; c < 4; ++c) {
        const std::uint64_t k = d * 4 + c;
        const bool live = m[d] > 0 && c < 3;
        r[k] = live ? m[d] * vstar[k] - q[k] : Real(0);
        p[k] = live ? m[d] * vstar[k] : Real(0);  // b, for its norm
      }
  });
  project(space, r);
  project(space, p);
  apply_preconditioner(space, p, z);
  const double bnorm = std::sqrt(std::max(dot(space, p, z), 0.0));
  // CG's stopping test is on the velocity error: z = D^-1 r estimates the error of x (exact
  // for the diagonal part), and its mass-weighted norm is compared with the velocities' own,
  // max(||v*||_M, ||x0||_M) (x0 carries prescribed collider velocities). A test on ||r||
  // relative to ||M v*|| instead amplifies float round-off in v* by (dt / dt_CFL)^2 and, for
  // stiff bodies at 10-30x the CFL step, sits at the tolerance (measured: 25 wasted iterations
  // per substep on a free-falling armadillo).
  const double vnorm = std::sqrt(std::max(mass_norm2(space, vstar), mass_norm2(space, x)));
  SolveStats st;
  if (!(bnorm > 0) || !(vnorm > 0)) {  // nothing moves: x0 is the solution
    st.converged = true;
    return st;
  }
  if (s.method == KrylovMethod::Minres) return minres(space, dt, s, bnorm, 0);

  apply_preconditioner(space, r, z);
  std::copy(z_.begin(), z_.end(), p_.begin());
  Dots dz = dots(space, r, z);
  double rz = dz.rz;
  const double eps = std::numeric_limits<double>::min();
  for (;;) {
    st.residual = std::sqrt(std::max(dz.mzz, 0.0)) / vnorm;
    if (st.residual <= s.tolerance) {
      st.converged = true;
      break;
    }
    if (!std::isfinite(st.residual))
      throw SimulationError("implicit solve: the residual is not finite (NaN state)");
    if (st.iterations >= s.max_iterations) break;
    apply(space, dt, p, q);
    project(space, q);
    const double pq = dot(space, p, q);
    if (!(pq > eps * std::max(1.0, rz))) {  // non-positive curvature: A is indefinite here
      SolveStats ms = minres(space, dt, s, bnorm, st.iterations);
      return ms;
    }
    const Real alpha = Real(rz / pq);
    exec::parallel_for(
        space, "implicit.cg_update", exec::Index(blocks_.size()), [=](exec::Index i) {
          const std::uint64_t b = blk[i].first * 4, e = b + std::uint64_t(blk[i].count) * 4;
          for (std::uint64_t k = b; k < e; ++k) {
            x[k] += alpha * p[k];
            r[k] -= alpha * q[k];
          }
        });
    apply_preconditioner(space, r, z);
    dz = dots(space, r, z);
    const double rz_new = dz.rz;
    const Real beta = Real(rz_new / rz);
    rz = rz_new;
    exec::parallel_for(
        space, "implicit.cg_direction", exec::Index(blocks_.size()), [=](exec::Index i) {
          const std::uint64_t b = blk[i].first * 4, e = b + std::uint64_t(blk[i].count) * 4;
          for (std::uint64_t k = b; k < e; ++k) p[k] = z[k] + beta * p[k];
        });
    ++st.iterations;
  }
  return st;
}

// Preconditioned MINRES from the current x (Paige & Saunders 1975, in the form of Choi's
// thesis / SciPy's minres), preconditioner D^{-1} (SPD), constraints projected. Stops when the
// estimated ||r||_{D^-1} falls below tolerance * bnorm.
SolveStats ImplicitSystem::minres(const exec::Space& space, Real dt, const ImplicitSettings& s,
                                  double bnorm, int used) {
  const std::size_t n4 = ndof_ * 4;
  for (auto* v : {&m_r1_, &m_r2_, &m_w_, &m_w1_, &m_w2_}) v->assign(n4, Real(0));
  const Block* blk = blocks_.data();
  const Real* m = mass_.data();
  const Real* vstar = vstar_.data();
  Real* x = x_.data();
  Real* r1 = m_r1_.data();
  Real* r2 = m_r2_.data();
  Real* y = z_.data();
  Real* v = p_.data();
  Real* w = m_w_.data();
  Real* w1 = m_w1_.data();
  Real* w2 = m_w2_.data();
  Real* tmp = q_.data();
  auto for_each = [&](const char* label, auto fn) {
    exec::parallel_for(space, label, exec::Index(blocks_.size()), [&](exec::Index i) {
      const std::uint64_t b = blk[i].first * 4, e = b + std::uint64_t(blk[i].count) * 4;
      for (std::uint64_t k = b; k < e; ++k) fn(k);
    });
  };
  // r1 = P (M v* - A x)
  apply(space, dt, x, tmp);
  for_each("implicit.minres_residual", [&](std::uint64_t k) {
    const std::uint64_t d = k / 4;
    r1[k] = (m[d] > 0 && k % 4 < 3) ? m[d] * vstar[k] - tmp[k] : Real(0);
  });
  project(space, r1);
  std::copy(m_r1_.begin(), m_r1_.end(), m_r2_.begin());
  apply_preconditioner(space, r1, y);
  const double beta1 = std::sqrt(std::max(dot(space, r1, y), 0.0));
  SolveStats st;
  st.used_minres = true;
  st.iterations = used;
  st.residual = beta1 / bnorm;
  if (st.residual <= s.tolerance) {
    st.converged = true;
    return st;
  }
  double oldb = 0, beta = beta1, dbar = 0, epsln = 0, phibar = beta1, cs = -1, sn = 0;
  while (st.iterations < s.max_iterations) {
    ++st.iterations;
    const Real sc = Real(1.0 / beta);
    for_each("implicit.minres_scale", [&](std::uint64_t k) { v[k] = sc * y[k]; });
    apply(space, dt, v, y);
    project(space, y);
    if (st.iterations - used >= 2) {
      const Real f = Real(beta / oldb);
      for_each("implicit.minres_axpy", [&](std::uint64_t k) { y[k] -= f * r1[k]; });
    }
    const double alfa = dot(space, v, y);
    const Real f2 = Real(alfa / beta);
    for_each("implicit.minres_lanczos", [&](std::uint64_t k) {
      y[k] -= f2 * r2[k];
      r1[k] = r2[k];
      r2[k] = y[k];
    });
    apply_preconditioner(space, r2, y);
    oldb = beta;
    beta = std::sqrt(std::max(dot(space, r2, y), 0.0));
    const double oldeps = epsln;
    const double delta = cs * dbar + sn * alfa;
    const double gbar = sn * dbar - cs * alfa;
    epsln = sn * beta;
    dbar = -cs * beta;
    const double gamma = std::max(std::hypot(gbar, beta), std::numeric_limits<double>::min());
    cs = gbar / gamma;
    sn = beta / gamma;
    const double phi = cs * phibar;
    phibar = sn * phibar;
    const Real a = Real(oldeps), dl = Real(delta), inv_g = Real(1.0 / gamma), ph = Real(phi);
    for_each("implicit.minres_update", [&](std::uint64_t k) {
      w1[k] = w2[k];
      w2[k] = w[k];
      w[k] = (v[k] - a * w1[k] - dl * w2[k]) * inv_g;
      x[k] += ph * w[k];
    });
    st.residual = phibar / bnorm;
    if (!std::isfinite(st.residual))
      throw SimulationError("implicit solve: the residual is not finite (NaN state)");
    if (st.residual <= s.tolerance) {
      st.converged = true;
      break;
    }
    if (!(beta > 0)) break;  // Krylov space exhausted
  }
  return st;
}

}  // namespace amalgam
