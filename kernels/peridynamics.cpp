#include "kernels/peridynamics.hpp"

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <new>
#include <type_traits>
#include <unordered_map>

#include <Eigen/QR>

#if defined(__SSE2__)
#include <xmmintrin.h>
#endif

namespace amalgam {

const char* pd_deviatoric_name(PdDeviatoric d) {
  return d == PdDeviatoric::Paper ? "paper" : "lps";
}

const char* pd_model_name(PdModel m) {
  return m == PdModel::Paper ? "paper" : "lps";
}

const char* pd_criterion_name(PdCriterion c) {
  return c == PdCriterion::Paper ? "paper" : "classical";
}

namespace {

// Cell binning for the neighbour search: sorted (cell key, particle) pairs, a cell's particles
// found by binary search (no dense cell array, so far-apart objects cost nothing).
struct CellIndex {
  Vec3d origin;
  double h;
  std::int64_t dims[3];
  std::vector<std::uint64_t> keys;      // sorted (sparse mode)
  std::vector<std::uint32_t> particle;  // particles in key order
  std::vector<std::uint32_t>
      start;  // dense mode: particles of cell k are particle[start[k]..start[k+1])
  std::uint64_t key(std::int64_t i, std::int64_t j, std::int64_t k) const {
    return (std::uint64_t(i) * std::uint64_t(dims[1]) + std::uint64_t(j)) * std::uint64_t(dims[2]) +
           std::uint64_t(k);
  }
  void cell_of(const Vec3& x, std::int64_t c[3]) const {
    for (int a = 0; a < 3; ++a)
      c[a] = std::min<std::int64_t>(
          dims[a] - 1, std::max<std::int64_t>(0, std::int64_t((double(x[a]) - origin[a]) / h)));
  }
};

CellIndex make_cells(const exec::Space& space, const Vec3* x, std::size_t n, double h) {
  CellIndex c;
  Vec3d lo = Vec3d::Constant(1e300), hi = Vec3d::Constant(-1e300);
  for (std::size_t i = 0; i < n; ++i) {
    lo = lo.cwiseMin(x[i].cast<double>());
    hi = hi.cwiseMax(x[i].cast<double>());
  }
  c.origin = lo;
  c.h = h;
  for (int a = 0; a < 3; ++a)
    c.dims[a] = std::max<std::int64_t>(1, std::int64_t((hi[a] - lo[a]) / h) + 1);
  std::vector<std::uint64_t> key(n);
  exec::parallel_for(space, "pd.cell_keys", exec::Index(n), [&](exec::Index i) {
    std::int64_t ci[3];
    c.cell_of(x[i], ci);
    key[std::size_t(i)] = c.key(ci[0], ci[1], ci[2]);
  });
  const double ncells = double(c.dims[0]) * double(c.dims[1]) * double(c.dims[2]);
  c.particle.resize(n);
  if (ncells <=
      8.0 * double(n) + 1e6) {  // dense: counting sort into a cell table (stable: index order)
    c.start.assign(std::size_t(ncells) + 1, 0);
    for (std::size_t i = 0; i < n; ++i) ++c.start[key[i] + 1];
    for (std::size_t k = 0; k + 1 < c.start.size(); ++k) c.start[k + 1] += c.start[k];
    std::vector<std::uint32_t> fill(c.start.begin(), c.start.end() - 1);
    for (std::size_t i = 0; i < n; ++i) c.particle[fill[key[i]]++] = std::uint32_t(i);
    return c;
  }
  // Sparse (far-apart particles): sorted (key, index) pairs, cells found by binary search.
  std::vector<std::pair<std::uint64_t, std::uint32_t>> order(n);
  for (std::size_t i = 0; i < n; ++i) order[i] = {key[i], std::uint32_t(i)};
  std::sort(order.begin(), order.end());  // a total order, so deterministic
  c.keys.resize(n);
  for (std::size_t i = 0; i < n; ++i) c.keys[i] = order[i].first, c.particle[i] = order[i].second;
  return c;
}

// Calls fn(j) for every particle j != i with |x_j - x_i| <= r (r <= cell size), in (cell, index)
// order.
template <class Fn>
void for_neighbours(const CellIndex& c, const Vec3* x, std::uint32_t i, Real r, Fn&& fn) {
  std::int64_t ci[3];
  c.cell_of(x[i], ci);
  const Real r2 = r * r;
  // Per (a, b) column the cells d0..d1 have consecutive keys: one binary search per column.
  const std::int64_t d0 = std::max<std::int64_t>(0, ci[2] - 1),
                     d1 = std::min(c.dims[2] - 1, ci[2] + 1);
  for (std::int64_t a = std::max<std::int64_t>(0, ci[0] - 1);
       a <= std::min(c.dims[0] - 1, ci[0] + 1); ++a)
    for (std::int64_t b = std::max<std::int64_t>(0, ci[1] - 1);
         b <= std::min(c.dims[1] - 1, ci[1] + 1); ++b) {
      const std::uint64_t k0 = c.key(a, b, d0), k1 = c.key(a, b, d1);
      std::size_t p0, p1;
      if (!c.start.empty()) {
        p0 = c.start[k0], p1 = c.start[k1 + 1];
      } else {
        p0 = std::size_t(std::lower_bound(c.keys.begin(), c.keys.end(), k0) - c.keys.begin());
        p1 = std::size_t(std::upper_bound(c.keys.begin() + std::ptrdiff_t(p0), c.keys.end(), k1) -
                         c.keys.begin());
      }
      for (std::size_t q = p0; q < p1; ++q) {
        const std::uint32_t j = c.particle[q];
        if (j != i && (x[j] - x[i]).squaredNorm() <= r2) fn(j);
      }
    }
}

// CSR rows of every particle's neighbours within r (rows sorted by index): a count pass, a
// scan and a fill pass over the cells. `what` prefixes the profiler labels.
struct RowLabels {
  const char *count, *scan, *fill;
};
void neighbour_rows(const exec::Space& space, const RowLabels& label, const Vec3* x, std::size_t n,
                    Real r, std::vector<std::uint64_t>& offsets,
                    std::vector<std::uint32_t>& neighbor) {
  offsets.assign(n + 1, 0);
  neighbor.clear();
  if (n == 0) return;
  const CellIndex cells = make_cells(space, x, n, double(r));
  std::vector<std::uint64_t> count(n);
  exec::parallel_for(space, label.count, exec::Index(n), [&](exec::Index i) {
    std::uint64_t c = 0;
    for_neighbours(cells, x, std::uint32_t(i), r, [&](std::uint32_t) { ++c; });
    count[std::size_t(i)] = c;
  });
  const std::uint64_t total = exec::parallel_scan<std::uint64_t>(
      space, label.scan, exec::Index(n), [&](exec::Index i) { return count[std::size_t(i)]; },
      offsets.data());
  offsets[n] = total;
  neighbor.resize(total);
  exec::parallel_for(space, label.fill, exec::Index(n), [&](exec::Index ii) {
    std::uint32_t* row = neighbor.data() + offsets[std::size_t(ii)];
    std::uint64_t c = 0;
    for_neighbours(cells, x, std::uint32_t(ii), r, [&](std::uint32_t j) { row[c++] = j; });
    std::sort(row, row + c);
  });
}

// reverse[k] = the index of bond j -> i for the bond k = i -> j (rows sorted, bonds symmetric).
void fill_reverse(const exec::Space& space, const char* label,
                  const std::vector<std::uint64_t>& off, const std::vector<std::uint32_t>& neighbor,
                  std::vector<std::uint64_t>& reverse) {
  reverse.resize(neighbor.size());
  const std::size_t n = off.empty() ? 0 : off.size() - 1;
  exec::parallel_for(space, label, exec::Index(n), [&](exec::Index ii) {
    const std::uint32_t i = std::uint32_t(ii);
    for (std::uint64_t k = off[i]; k < off[i + 1]; ++k) {
      const std::uint32_t j = neighbor[k];
      const std::uint32_t* b = neighbor.data() + off[j];
      const std::uint32_t* e = neighbor.data() + off[j + 1];
      reverse[k] = off[j] + std::uint64_t(std::lower_bound(b, e, i) - b);
    }
  });
}

}  // namespace

void pd_build_bonds(const exec::Space& space, const Vec3* x0, const Real* volume,
                    const std::int32_t* material, std::size_t n, const PdParams& prm,
                    bool partial_volume, PdBonds& bonds) {
  const Real delta = prm.horizon, lc = prm.spacing;
  neighbour_rows(space, {"pd.bond_count", "pd.bond_scan", "pd.bond_fill"}, x0, n, delta,
                 bonds.offsets, bonds.neighbor);
  const std::size_t total = bonds.neighbor.size();
  bonds.length.resize(total);
  bonds.omega.resize(total);
  bonds.volume.resize(total);
  bonds.plastic.assign(total, Real(0));
  bonds.intact.assign(total, 1);
  bonds.lane.resize(total);
  bonds.dense.assign(n, 1);
  const std::uint64_t* off = bonds.offsets.data();
  exec::parallel_for(space, "pd.bond_geometry", exec::Index(n), [&](exec::Index ii) {
    const std::size_t i = std::size_t(ii);
    const Mat3& G = prm.materials[material[i]].G;
    for (std::uint64_t k = off[i]; k < off[i + 1]; ++k) {
      const std::uint32_t j = bonds.neighbor[k];
      const Vec3 xi = x0[j] - x0[i];
      const Real L = xi.norm();
      bonds.length[k] = L;
      bonds.omega[k] = delta / (G * xi).norm();  // eq. 16 (eq. 4 when G = I)
      Real nu = 1;
      if (partial_volume && L > delta - lc / 2) nu = std::min(Real(1), (delta + lc / 2 - L) / lc);
      bonds.volume[k] = nu * volume[j];
      bonds.lane[k] = std::uint8_t((k - off[i]) % kSumLanes);
    }
  });
  fill_reverse(space, "pd.bond_reverse", bonds.offsets, bonds.neighbor, bonds.reverse);
}

namespace {

// The correction's fit (see PdConstants): positive factors h_k = exp(lambda . phi(k)), the
// closest to 1 in relative entropy sum_k w_k (h_k log h_k - h_k + 1), under the moment
// constraints sum_k w_k h_k phi(k) = target. lambda minimises the convex dual sum_k w_k h_k -
// lambda . target: Newton with backtracking from lambda = 0 (h = 1). Returns false when the
// family cannot meet the constraints (too few directions, as in a sheet one layer thick: the
// Hessian is singular or the iteration does not converge) or when the largest factor exceeds
// 8 times the mean (a few bonds would carry the particle: too stiff for the time step).
// Near the solution the decrease a Newton step promises (half the decrement grad . step) falls
// below the round-off of the dual, so the backtracking test can no longer judge it: such steps
// are taken whole (Newton converges quadratically there). Once the gradient is within tol, one
// more whole step takes lambda to round-off. Both matter for mirror images: two families that
// differ only in the order of their bonds (a family and its mirror image, rows sorted by
// index) sum in different orders, so a test of the dual's round-off could fail for one and pass
// for the other, and a fit stopped at tol leaves factors that differ by ~1e-8. Before, a
// notch-corner family of the notched bar (bench/pd_notch.cpp) had its full fit rejected on one
// side only (the backtracking failed on round-off one step before tol) and fell back to the
// axis-diagonal fit, dilatational factors up to 20x apart from its mirror image's: the bar's
// response lost its mirror symmetry by ~10 % of the displacement at that corner.
template <int N, class Basis>
bool fit_factors(std::uint64_t k0, std::uint64_t k1, const double* w, Basis&& basis,
                 const Eigen::Matrix<double, N, 1>& target, std::vector<double>& h) {
  using Vec = Eigen::Matrix<double, N, 1>;
  using Mat = Eigen::Matrix<double, N, N>;
  const std::size_t nb = std::size_t(k1 - k0);
  std::vector<Vec> phi(nb);
  for (std::size_t k = 0; k < nb; ++k) phi[k] = basis(k0 + k);
  h.assign(nb, 1.0);
  Vec lambda = Vec::Zero();
  auto dual = [&](const Vec& l) {
    double F = -l.dot(target);
    for (std::size_t k = 0; k < nb; ++k) F += w[k] * std::exp(phi[k].dot(l));
    return F;
  };
  auto accept = [&] {
    double mean = 0, hi = 0;
    for (double v : h) mean += v / double(nb), hi = std::max(hi, v);
    return hi <= 8 * mean;
  };
  double F = dual(lambda);
  const double tol =
      1e-8 * target.norm();  // well above the round-off of the sums (~1e-14 relative)
  for (int it = 0; it < 60; ++it) {
    Vec grad = -target;
    Mat hess = Mat::Zero();
    double scale = 0;  // sum_k w_k h_k: the size of the dual's terms (its round-off ~1e-16 of it)
    for (std::size_t k = 0; k < nb; ++k) {
      grad += w[k] * h[k] * phi[k];
      scale += w[k] * h[k];
      hess.template selfadjointView<Eigen::Upper>().rankUpdate(phi[k], w[k] * h[k]);
    }
    const bool converged = grad.norm() <= tol;
    hess.template triangularView<Eigen::StrictlyLower>() = hess.transpose();
    const Eigen::ColPivHouseholderQR<Mat> qr(hess);
    if (qr.rank() < N) return converged && accept();
    const Vec step = qr.solve(grad);
    double t = 1;
    if (converged || grad.dot(step) <= 1e-12 * scale) {  // a whole step (see above)
      F = dual(lambda - step);
    } else {
      for (; t > 1e-8; t *= 0.5) {  // backtracking (Armijo) on the dual
        const double Ft = dual(lambda - t * step);
        if (Ft <= F - 1e-4 * t * grad.dot(step)) {
          F = Ft;
          break;
        }
      }
      if (!(t > 1e-8)) return false;
    }
    lambda -= t * step;
    for (std::size_t k = 0; k < nb; ++k) h[k] = std::exp(phi[k].dot(lambda));
    if (converged) return accept();
  }
  return false;
}

// Monomials n_a n_b (a <= b) and n_a n_b n_c n_d (a <= b <= c <= d) of a direction, and the
// same moments of the isotropic distribution (the unit sphere average times the scale).
void monomials2(const Vec3d& n, double* out) {
  int c = 0;
  for (int a = 0; a < 3; ++a)
    for (int b = a; b < 3; ++b) out[c++] = n[a] * n[b];
}
void monomials4(const Vec3d& n, double* out) {
  int c = 0;
  for (int a = 0; a < 3; ++a)
    for (int b = a; b < 3; ++b)
      for (int d = b; d < 3; ++d)
        for (int e = d; e < 3; ++e) out[c++] = n[a] * n[b] * n[d] * n[e];
}
// delta_ab, and delta_ab delta_de + delta_ad delta_be + delta_ae delta_bd (= 3 for xxxx, 1 for xxyy).
void isotropic2(double* out) {
  int c = 0;
  for (int a = 0; a < 3; ++a)
    for (int b = a; b < 3; ++b) out[c++] = a == b ? 1 : 0;
}
void isotropic4(double* out) {
  int c = 0;
  for (int a = 0; a < 3; ++a)
    for (int b = a; b < 3; ++b)
      for (int d = b; d < 3; ++d)
        for (int e = d; e < 3; ++e)
          out[c++] = double((a == b) * (d == e) + (a == d) * (b == e) + (a == e) * (b == d));
}

}  // namespace

void pd_constants(const exec::Space& space, const Vec3* x0, const std::int32_t* material,
                  PdBonds& bonds, const PdParams& prm, bool surface_correction, PdConstants& out) {
  const std::size_t n = bonds.particles();
  out.m.resize(n);
  out.a.resize(n);
  out.b.resize(n);
  out.kappa.resize(n);
  out.bonds0.resize(n);
  out.fitted.assign(n, 0);
  bonds.shear_omega.resize(bonds.size());
  const double delta = double(prm.horizon);
  const double m_cont = 4.0 * M_PI * std::pow(delta, 4) / 3.0;  // eq. 5: 3 / m = 9 / (4 pi delta^4)
  const double s_cont = M_PI * std::pow(delta, 5) / 15.0;       // continuum M_xxyy of omega L^2
  const double b_unit = 15.0 / (2.0 * M_PI * std::pow(delta, 5));  // eq. 9 per unit shear modulus
  // Targets: continuum moments of the isotropic weight omega0 = delta / L (eq. 4).
  Eigen::Matrix<double, 6, 1> t_dil;
  Eigen::Matrix<double, 21, 1> t_dev;
  isotropic2(t_dil.data());
  t_dil *= m_cont / 3 / delta;  // sum omega L n_a n_b V (lengths in units of delta below)
  isotropic4(t_dev.data());
  t_dev.head<15>() *= s_cont / (delta * delta);  // sum omega L^2 n_a n_b n_c n_d V
  isotropic2(t_dev.data() + 15);
  t_dev.tail<6>() *=
      m_cont / 3 / delta;  // sum omega L n_a n_b V (the paper's form: e^d exact under dilation)
  // Particles with the same family (material, bond vectors and volumes, to 1e-6 of delta and of
  // the largest volume) share one fit: on a lattice only the few hundred distinct positions
  // relative to the faces are fitted. The representative is the lowest index, so the result does
  // not depend on the thread count.
  double vmax = 0;
  for (std::size_t k = 0; k < bonds.size(); ++k) vmax = std::max(vmax, double(bonds.volume[k]));
  auto signature = [&](std::size_t i) {
    std::vector<std::int64_t> sig{std::int64_t(material[i]),
                                  std::int64_t(bonds.offsets[i + 1] - bonds.offsets[i])};
    for (std::uint64_t k = bonds.offsets[i]; k < bonds.offsets[i + 1]; ++k) {
      const Vec3d xi = (x0[bonds.neighbor[k]] - x0[i]).cast<double>() / (1e-6 * delta);
      for (int a = 0; a < 3; ++a) sig.push_back(std::llround(xi[a]));
      sig.push_back(std::llround(double(bonds.volume[k]) / (1e-6 * vmax + 1e-300)));
    }
    return sig;
  };
  std::vector<std::uint64_t> key(n);
  exec::parallel_for(space, "pd.constants_keys", exec::Index(n), [&](exec::Index ii) {
    const std::vector<std::int64_t> sig = signature(std::size_t(ii));
    std::uint64_t h = 1469598103934665603ull;  // FNV-1a over the signature
    for (std::int64_t v : sig)
      for (int b = 0; b < 8; ++b)
        h = (h ^ ((std::uint64_t(v) >> (8 * b)) & 0xff)) * 1099511628211ull;
    key[std::size_t(ii)] = h;
  });
  std::vector<std::uint32_t> rep(n);
  {
    std::unordered_map<std::uint64_t, std::uint32_t> first;
    for (std::size_t i = 0; i < n; ++i)
      rep[i] = first.emplace(key[i], std::uint32_t(i)).first->second;
  }
  exec::parallel_for(space, "pd.constants_verify", exec::Index(n), [&](exec::Index ii) {
    const std::size_t i = std::size_t(ii);
    if (rep[i] != i && signature(i) != signature(rep[i]))
      rep[i] = std::uint32_t(i);  // a hash collision
  });
  exec::parallel_for(space, "pd.constants", exec::Index(n), [&](exec::Index ii) {
    const std::size_t i = std::size_t(ii);
    if (rep[i] != i) return;  // copied from its representative below
    const std::uint64_t k0 = bonds.offsets[i], k1 = bonds.offsets[i + 1];
    double m = m_cont, kappa = delta / 4;
    std::uint8_t fitted = 0;
    const PdMaterial& mat = prm.materials[material[i]];
    if (prm.model == PdModel::Lps) {  // Silling et al. 2007: m_i over the particle's own family
      double ml = 0;
      for (std::uint64_t k = k0; k < k1; ++k) {
        const double L = double(bonds.length[k]);
        ml += double(bonds.omega[k]) * L * L * double(bonds.volume[k]);
        bonds.shear_omega[k] = bonds.omega[k];
      }
      // A particle without bonds feels no bond force (a = b = 0 rather than a division by 0).
      out.m[i] = Real(ml > 0 ? ml : m_cont * delta);
      out.a[i] = ml > 0 ? Real(1.5 * double(mat.bulk) / ml) : Real(0);
      out.b[i] = ml > 0 ? Real(7.5 * double(mat.shear) / ml) : Real(0);
      out.kappa[i] = 0;
      out.bonds0[i] = std::int32_t(k1 - k0);
      out.fitted[i] = 0;
      return;
    }
    if (surface_correction && k1 > k0) {
      const std::size_t nb = std::size_t(k1 - k0);
      std::vector<double> w(nb), L(nb), g, f;
      std::vector<Vec3d> dir(nb);
      for (std::uint64_t k = k0; k < k1; ++k) {
        const Vec3d xi = (x0[bonds.neighbor[k]] - x0[i]).cast<double>();
        L[k - k0] = xi.norm();
        dir[k - k0] = xi / L[k - k0];
        w[k - k0] = delta / L[k - k0] * double(bonds.volume[k]);  // isotropic omega0 V (eq. 4)
      }
      auto basis_dil = [&](std::uint64_t k) {
        Eigen::Matrix<double, 6, 1> phi;
        monomials2(dir[k - k0], phi.data());
        return Eigen::Matrix<double, 6, 1>(phi * (L[k - k0] / delta));
      };
      auto basis_dev = [&](std::uint64_t k) {
        Eigen::Matrix<double, 21, 1> phi;
        monomials4(dir[k - k0], phi.data());
        monomials2(dir[k - k0], phi.data() + 15);
        phi.head<15>() *= (L[k - k0] / delta) * (L[k - k0] / delta);
        phi.tail<6>() *= L[k - k0] / delta;
        return phi;
      };
      // The axis-diagonal moments only (xx, yy, zz; xxxx, yyyy, zzzz, xxyy, yyzz, zzxx), for
      // families cut by two faces (an edge): there the cross moments such as yz cannot vanish
      // with positive weights (every bond has n_y, n_z >= 0).
      auto basis_dil3 = [&](std::uint64_t k) {
        return Eigen::Vector3d(dir[k - k0].cwiseAbs2() * (L[k - k0] / delta));
      };
      auto basis_dev9 = [&](std::uint64_t k) {
        const Vec3d q = dir[k - k0].cwiseAbs2();
        const double l = L[k - k0] / delta;
        Eigen::Matrix<double, 9, 1> phi;
        phi << q[0] * q[0], q[1] * q[1], q[2] * q[2], q[0] * q[1], q[1] * q[2], q[2] * q[0], q[0],
            q[1], q[2];
        phi.head<6>() *= l * l;
        phi.tail<3>() *= l;
        return phi;
      };
      Eigen::Matrix<double, 9, 1> t_dev9;
      t_dev9 << 3, 3, 3, 1, 1, 1, 0, 0, 0;
      t_dev9.head<6>() *= s_cont / (delta * delta);
      t_dev9.tail<3>().setConstant(m_cont / 3 / delta);
      // Dilatation: the full fit, else the diagonal one, else LPS's discrete normaliser m_i.
      const bool dil_full = fit_factors<6>(k0, k1, w.data(), basis_dil, t_dil, g);
      const bool dil = dil_full || fit_factors<3>(k0, k1, w.data(), basis_dil3,
                                                  Eigen::Vector3d(t_dil[0], t_dil[3], t_dil[5]), g);
      if (!dil) g.assign(nb, 1.0);
      // Deviatoric: the full fit, else the diagonal one, else one factor for the mean coordinate
      // shear sum (kappa then from the family).
      const bool dev_full = dil_full && fit_factors<21>(k0, k1, w.data(), basis_dev, t_dev, f);
      const bool dev = dev_full || (dil && fit_factors<9>(k0, k1, w.data(), basis_dev9, t_dev9, f));
      fitted = dev_full ? 2 : dev ? 1 : 0;
      if (!dev) {
        double ss = 0;
        for (std::size_t k = 0; k < nb; ++k) {
          const Vec3d q = dir[k].cwiseAbs2();
          ss += w[k] * L[k] * L[k] * (q[0] * q[1] + q[1] * q[2] + q[2] * q[0]) / 3;
        }
        f.assign(nb, ss > 0 ? s_cont / ss : 1.0);
      }
      double ms = 0, mf = 0, m2f = 0;
      for (std::uint64_t k = k0; k < k1; ++k) {
        const double om = double(bonds.omega[k]);  // keeps the material's anisotropy (eq. 16)
        const double wk = om * double(bonds.volume[k]), l = L[k - k0];
        ms += wk * l;
        mf += wk * f[k - k0] * l;
        m2f += wk * f[k - k0] * l * l;
        bonds.omega[k] = Real(om * g[k - k0]);
        bonds.shear_omega[k] = Real(om * f[k - k0]);
      }
      if (!dil && ms > 0) m = ms;
      if (!dev && mf > 0) kappa = m2f / (3 * mf);
    } else {
      for (std::uint64_t k = k0; k < k1; ++k) bonds.shear_omega[k] = bonds.omega[k];
    }
    // With the consistent term (PdParams::consistent), the paper's e^d is not zero under a
    // dilation (e^d = eps (L - 3 kappa) bond by bond), so q adds a dilatational stiffness: under
    // theta = 3 eps, q = (b / m) theta sum_j shear_omega (L - 3 d) d V_j (d = kappa; 0 for LPS,
    // whose e^d vanishes). a absorbs it, so that a theta - q keeps K exact.
    double a_extra = 0;
    if (surface_correction && prm.deviatoric == PdDeviatoric::Paper) {
      double r = 0;
      for (std::uint64_t k = k0; k < k1; ++k)
        r += double(bonds.shear_omega[k]) * (double(bonds.length[k]) - 3 * kappa) * kappa *
             double(bonds.volume[k]);
      a_extra = b_unit * double(mat.shear) * r / m;
    }
    out.m[i] = Real(m);
    out.a[i] = Real(1.5 * double(mat.bulk) / m + a_extra);
    out.b[i] = Real(b_unit * double(mat.shear));
    out.kappa[i] = Real(kappa);
    out.bonds0[i] = std::int32_t(k1 - k0);
    out.fitted[i] = fitted;
  });
  exec::parallel_for(space, "pd.constants_copy", exec::Index(n), [&](exec::Index ii) {
    const std::size_t i = std::size_t(ii), r = rep[i];
    if (r == i) return;
    out.m[i] = out.m[r], out.a[i] = out.a[r], out.b[i] = out.b[r], out.kappa[i] = out.kappa[r];
    out.bonds0[i] = out.bonds0[r], out.fitted[i] = out.fitted[r];
    for (std::uint64_t k = bonds.offsets[i], q = bonds.offsets[r]; k < bonds.offsets[i + 1];
         ++k, ++q) {
      bonds.omega[k] = bonds.omega[q];
      bonds.shear_omega[k] = bonds.shear_omega[q];
    }
  });
  pd_mirror_bonds(space, bonds);
}

void pd_mirror_bonds(const exec::Space& space, PdBonds& bonds) {
  const std::size_t nb = bonds.size();
  bonds.omega_r.resize(nb);
  bonds.shear_omega_r.resize(nb);
  bonds.plastic_r.resize(nb);
  exec::parallel_for(space, "pd.mirror", exec::Index(nb), [&](exec::Index kk) {
    const std::size_t k = std::size_t(kk), r = std::size_t(bonds.reverse[k]);
    bonds.omega_r[k] = bonds.omega[r];
    bonds.shear_omega_r[k] = bonds.shear_omega[r];
    bonds.plastic_r[k] = bonds.plastic[r];
  });
}

namespace {

// Bond blocks (the force pass below and the dilatation pass): a row is processed in blocks; a
// scalar loop gathers what the neighbour j indexes (positions, its constants) into local arrays,
// a branch-free loop over the block, reading the per-bond arrays in place, is vectorised by the
// compiler (sqrt and division included: IEEE-exact in SIMD), then sums run over the row in lanes
// (PdBonds::lane), each lane in bond order. Broken bonds add exact zeros (x + 0 = x, and +0 + -0 =
// +0 from the +0 start), so every lane sum equals the one that skips them: results do not depend
// on the backend, the thread count or whether broken bonds were compacted away.
constexpr int kBlock = 64;      // force pass
constexpr int kDilBlock = 256;  // dilatation pass: a whole row of up to 256 bonds (delta < 3.9 lc)
                                // stays in one block for the plastic return
static_assert(kBlock % kSumLanes == 0 && kDilBlock % kSumLanes == 0, "blocks start on lane 0");

// Gathers per neighbour: the first Q 16-byte quads of per-particle records, four neighbours at a
// time, every quad of a record loaded from one address (one index load and one address per
// neighbour for all Q quads). out[q][c][m] = rec(idx[m]).quad[q][c] - sub[q][c] for m < n
// (records `stride` bytes apart, 16-byte aligned; sub null: nothing subtracted, for the last
// quad when `last_raw`). SSE: four records per step loaded whole and transposed (4 loads, 8
// shuffles, 4 stores for 16 values instead of 16 scalar loads and stores); the same values as
// the scalar loop.
template <int Q, bool LastRaw>
void gather_records(const void* records, std::size_t stride, const std::uint32_t* idx, int n,
                    const Real (*sub)[4], Real* const (*out)[4]) {
  const char* base = static_cast<const char*>(records);
  int m = 0;
#if defined(__SSE2__) && !defined(AMALGAM_REAL_DOUBLE)
  __m128 sv[Q];
  for (int q = 0; q < Q; ++q) sv[q] = _mm_loadu_ps(sub[q]);
  for (; m + 4 <= n; m += 4) {
    const float* r0 = reinterpret_cast<const float*>(base + std::size_t(idx[m]) * stride);
    const float* r1 = reinterpret_cast<const float*>(base + std::size_t(idx[m + 1]) * stride);
    const float* r2 = reinterpret_cast<const float*>(base + std::size_t(idx[m + 2]) * stride);
    const float* r3 = reinterpret_cast<const float*>(base + std::size_t(idx[m + 3]) * stride);
    for (int q = 0; q < Q; ++q) {
      __m128 a = _mm_load_ps(r0 + 4 * q), b = _mm_load_ps(r1 + 4 * q), c = _mm_load_ps(r2 + 4 * q),
             d = _mm_load_ps(r3 + 4 * q);
      if (!(LastRaw && q == Q - 1)) {
        a = _mm_sub_ps(a, sv[q]), b = _mm_sub_ps(b, sv[q]), c = _mm_sub_ps(c, sv[q]);
        d = _mm_sub_ps(d, sv[q]);
      }
      _MM_TRANSPOSE4_PS(a, b, c, d);
      _mm_storeu_ps(out[q][0] + m, a), _mm_storeu_ps(out[q][1] + m, b);
      _mm_storeu_ps(out[q][2] + m, c), _mm_storeu_ps(out[q][3] + m, d);
    }
  }
#endif
  for (; m < n; ++m) {
    const Real* r = reinterpret_cast<const Real*>(base + std::size_t(idx[m]) * stride);
    for (int q = 0; q < Q; ++q)
      for (int c = 0; c < 4; ++c)
        out[q][c][m] = (LastRaw && q == Q - 1) ? r[4 * q + c] : r[4 * q + c] - sub[q][c];
  }
}

// Lane sums (PdBonds::lane): acc[lane] += t[m] over a block of n terms, in bond order within each
// lane. Dense rows: lane = position mod kSumLanes (blocks start at multiples of kSumLanes), 8
// independent chains the compiler vectorises. Compacted rows: the stored lanes (scalar).
inline void lane_sum(const Real* t, int n, Real* acc) {
  int m = 0;
  for (; m + kSumLanes <= n; m += kSumLanes)
    for (int l = 0; l < kSumLanes; ++l) acc[l] += t[m + l];
  for (int l = 0; m + l < n; ++l) acc[l] += t[m + l];
}
inline void lane_sum(const Real* t, const std::uint8_t* lane, int n, Real* acc) {
  for (int m = 0; m < n; ++m) acc[lane[m]] += t[m];
}
inline void lane_sum(const Real* t, const std::uint8_t* lane, bool dense, int n, Real* acc) {
  if (dense)
    lane_sum(t, n, acc);
  else
    lane_sum(t, lane, n, acc);
}
// The lanes combined in a fixed order.
inline Real lane_total(const Real* a) {
  static_assert(kSumLanes == 8, "lane_total combines 8 lanes");
  return ((a[0] + a[1]) + (a[2] + a[3])) + ((a[4] + a[5]) + (a[6] + a[7]));
}

// The displacement u = (x - x0) + x_lo the bond passes read: eta = xi + (u_j - u_i) keeps the
// increments that x alone rounds away far from the origin (x - x0 is exact while x is within a
// factor 2 of x0, and xi = x0_j - x0_i is exact between neighbours).
inline Vec3 displacement(const PdView& p, std::size_t i) {
  const Vec3 u = p.x[i] - p.x0[i];
  return p.x_lo ? Vec3(u + p.x_lo[i]) : u;
}

// What the dilatation pass gathers per neighbour.
struct alignas(16) PosRec {
  Real y[4];   // displacement u, 0
  Real x0[4];  // reference position, 0
};

// Gathered per block: the neighbour's current and reference position; the per-bond arrays are
// read in place (DilSlice).
struct DilBlock {
  alignas(64) Real ex[kDilBlock], ey[kDilBlock], ez[kDilBlock];     // u_j - u_i (eta - xi)
  alignas(64) Real xx[kDilBlock], xy[kDilBlock], xz[kDilBlock];     // xi = x0_j - x0_i
  alignas(64) Real pad[kDilBlock];                                  // the gathers' unused lane
  alignas(64) Real e[kDilBlock], lambda[kDilBlock], ok[kDilBlock];  // geometry (0 for dead bonds)
  alignas(64) Real t[kDilBlock], w1[kDilBlock], w2[kDilBlock], w3[kDilBlock];  // terms of the sums
  alignas(64) Real ep_new[kDilBlock];                                          // plastic return
};
struct DilSlice {
  const Real *L, *omega, *shear, *vol, *ep;
  const std::uint8_t* live;
};

void gather_dilatation(const PosRec* recs, const PdBonds& bonds, std::uint64_t kb, int n,
                       const Real sub_y[4], const Real sub_x0[4], DilBlock& B) {
  const Real sub[2][4] = {{sub_y[0], sub_y[1], sub_y[2], sub_y[3]},
                          {sub_x0[0], sub_x0[1], sub_x0[2], sub_x0[3]}};
  Real* const out[2][4] = {{B.ex, B.ey, B.ez, B.pad}, {B.xx, B.xy, B.xz, B.pad}};
  gather_records<2, false>(recs, sizeof(PosRec), bonds.neighbor.data() + kb, n, sub, out);
}

// e, Lambda (eqs. 3, 6) and the terms of theta (eq. 5) and of the consistent sums (see header):
// w = shear_omega V d with d = kappa Lambda (paper) or L / 3 (LPS).
template <bool Paper, bool Plastic, bool Lps>
void dilatation_block(DilBlock& B, const DilSlice& S, int n, Real kappa) {
  for (int m = 0; m < n; ++m) {  // vectorised
    const Real ex = B.xx[m] + B.ex[m], ey = B.xy[m] + B.ey[m], ez = B.xz[m] + B.ez[m];  // eta
    const Real l2 = ex * ex + ey * ey + ez * ez;
    const bool ok = (l2 > 0) & (S.live[m] != 0);  // coincident particles: no direction
    const Real l = std::sqrt(ok ? l2 : Real(1));
    const Real L = S.L[m];
    const Real live = ok ? Real(1) : Real(0);  // times 0, not a select (see force_block)
    const Real e = live * (l - L);
    const Real lambda = live * ((ex * B.xx[m] + ey * B.xy[m] + ez * B.xz[m]) / (l * L));
    B.e[m] = e, B.lambda[m] = lambda, B.ok[m] = live;
    // omega s Lambda |xi| V (eq. 5), s = e / |xi|; PdModel::Lps: omega |xi| e V (Silling et al.
    // 2007 eq. 4.3)
    B.t[m] = S.omega[m] * e * (Lps ? L : lambda) * S.vol[m];
    const Real d = Paper ? kappa * lambda : L / Real(3);
    const Real w = live * (S.shear[m] * S.vol[m] * d);
    B.w1[m] = w * e, B.w2[m] = w * d;
    if (Plastic) B.w3[m] = w * S.ep[m];  // else every ep = 0: the sum s3 is +0
  }
}

// The plastic return (eqs. 11-15) of every live bond of the block: B.ep_new the new plastic
// extension, B.t the term of Q (see header). (Not in place: a conditional store would stop the
// vectorisation.)
template <bool Paper>
void plastic_block(DilBlock& B, const DilSlice& S, int n, Real theta, Real kappa, Real stiff_i,
                   Real psi0, Real ac, Real cap_ratio) {
  for (int m = 0; m < n; ++m) {  // vectorised
    const Real e = B.e[m], lambda = B.lambda[m], L = S.L[m];
    const Real ed = Paper ? e - kappa * lambda * theta : e - theta * L / Real(3);  // eq. 8 / LPS
    const Real stiff = stiff_i * S.shear[m];                                       // 4 omega b
    const Real ep = S.ep[m];
    const Real adev = stiff * (ed - ep);                         // eq. 11
    const bool yield = Real(0.5) * adev * adev > psi0;           // eq. 12
    const Real flow = (adev - std::copysign(ac, adev)) / stiff;  // eqs. 13-14 (exact return)
    const Real ep1 = yield ? ep + flow : ep;
    const Real cap = cap_ratio * L;  // eq. 15
    const Real ep2 = std::copysign(std::min(std::abs(ep1), cap), ep1);
    const bool ok = B.ok[m] != 0;
    B.ep_new[m] = ok ? ep2 : ep;
    B.t[m] =
        B.ok[m] * (S.shear[m] * (ed - ep2) * (Paper ? kappa * lambda : L / Real(3)) * S.vol[m]);
  }
}

// fn(std::true_type{}) or fn(std::false_type{}): a run-time flag as a template argument.
template <class Fn>
void with_flag(bool flag, Fn&& fn) {
  if (flag)
    fn(std::true_type{});
  else
    fn(std::false_type{});
}

// fn(paper, lps) with the model's form as template arguments: the paper's deviatoric extension
// (Paper), the dilatation along |xi| instead of Lambda (Lps: PdModel::Lps, whose deviatoric
// extension is always LPS's). Three combinations, so three instantiations, not four.
template <class Fn>
void with_form(const PdParams& prm, Fn&& fn) {
  if (prm.model == PdModel::Lps)
    fn(std::false_type{}, std::true_type{});
  else if (prm.deviatoric == PdDeviatoric::Paper)
    fn(std::true_type{}, std::false_type{});
  else
    fn(std::false_type{}, std::false_type{});
}

// n records of type Rec in the caller's scratch (reused, not zeroed: every record is written
// before it is read), or in `local` when there is none.
template <class Rec>
Rec* scratch_records(PdScratch* scratch, std::vector<Real>& local, std::size_t n) {
  static_assert(sizeof(Rec) % sizeof(Real) == 0 && alignof(Rec) <= __STDCPP_DEFAULT_NEW_ALIGNMENT__,
                "Real storage");
  std::vector<Real>& v = scratch ? scratch->records : local;
  const std::size_t need = n * (sizeof(Rec) / sizeof(Real));
  if (v.size() < need) v.resize(need);
  return reinterpret_cast<Rec*>(v.data());
}

}  // namespace

void pd_dilatation(const exec::Space& space, const PdView& p, PdBonds& bonds, const PdParams& prm,
                   PdScratch* scratch) {
  const bool consistent = prm.consistent;
  std::vector<Real> local;
  PosRec* const recs = scratch_records<PosRec>(scratch, local, p.n);
  exec::parallel_for(space, "pd.dilatation_rows", exec::Index(p.n), [&](exec::Index i) {
    const Vec3 u = displacement(p, std::size_t(i));
    ::new (static_cast<void*>(recs + i))
        PosRec{{u[0], u[1], u[2], 0}, {p.x0[i][0], p.x0[i][1], p.x0[i][2], 0}};
  });
  auto kernel = [&](auto paper_c, auto plastic_c, auto lps_c) {
    constexpr bool Paper = decltype(paper_c)::value, Plastic = decltype(plastic_c)::value;
    constexpr bool Lps = decltype(lps_c)::value;
    exec::parallel_for(space, "pd.dilatation", exec::Index(p.n), [&](exec::Index ii) {
      const std::size_t i = std::size_t(ii);
      const std::uint64_t k0 = bonds.offsets[i], k1 = bonds.offsets[i + 1];
      const Real sub_y[4] = {recs[i].y[0], recs[i].y[1], recs[i].y[2], 0};
      const Real sub_x0[4] = {p.x0[i][0], p.x0[i][1], p.x0[i][2], 0};
      const Real kap = p.kappa[i];
      const bool one_block = k1 - k0 <= std::uint64_t(kDilBlock);
      DilBlock B;
      auto slice = [&](std::uint64_t kb) {
        return DilSlice{bonds.length.data() + kb,      bonds.omega.data() + kb,
                        bonds.shear_omega.data() + kb, bonds.volume.data() + kb,
                        bonds.plastic.data() + kb,     bonds.intact.data() + kb};
      };
      auto load = [&](std::uint64_t kb) {
        const int n = int(std::min<std::uint64_t>(kDilBlock, k1 - kb));
        gather_dilatation(recs, bonds, kb, n, sub_y, sub_x0, B);
        dilatation_block<Paper, Plastic, Lps>(B, slice(kb), n, kap);
        return n;
      };
      const PdMaterial& mat = prm.materials[p.material[i]];
      const bool plastic = Plastic && mat.psi0 < std::numeric_limits<Real>::infinity();
      // s1..s3: the consistent term's sums (see header); a plastic particle's q comes from the
      // plastic return below instead.
      const bool sums = consistent && !plastic;
      const bool dense = bonds.dense[i] != 0;
      alignas(32) Real a0[kSumLanes] = {}, a1[kSumLanes] = {}, a2[kSumLanes] = {},
                       a3[kSumLanes] = {};
      for (std::uint64_t kb = k0; kb < k1; kb += kDilBlock) {
        const int n = load(kb);
        const std::uint8_t* lane = bonds.lane.data() + kb;
        lane_sum(B.t, lane, dense, n, a0);
        if (sums) lane_sum(B.w1, lane, dense, n, a1), lane_sum(B.w2, lane, dense, n, a2);
        if (sums && Plastic) lane_sum(B.w3, lane, dense, n, a3);
      }
      const Real sum = lane_total(a0), s1 = lane_total(a1), s2 = lane_total(a2),
                 s3 = lane_total(a3);
      const Real theta = Real(3) * sum / p.m[i];
      p.theta[i] = theta;
      const Real qscale = p.b[i] * Real(3) / p.m[i];
      if (sums) p.q[i] = qscale * (s1 - theta * s2 - s3);
      if (!plastic) return;
      Real Q = 0;
      const Real ac = std::sqrt(Real(2) * mat.psi0);
      for (std::uint64_t kb = k0; kb < k1; kb += kDilBlock) {
        const int n = one_block ? int(k1 - k0) : load(kb);  // one block: still loaded
        plastic_block<Paper>(B, slice(kb), n, theta, kap, Real(4) * p.b[i], mat.psi0, ac,
                             mat.plastic_cap);
        for (int m = 0; m < n; ++m) {
          const std::uint64_t k = kb + std::uint64_t(m);
          if (B.ep_new[m] !=
              bonds.plastic[k]) {  // yielded: row j's force pass reads it from plastic_r
            bonds.plastic[k] = B.ep_new[m];
            // (kNoReverse: row j is another rank's, which receives it by its bond halo)
            if (bonds.reverse[k] != kNoReverse) bonds.plastic_r[bonds.reverse[k]] = B.ep_new[m];
          }
          Q += B.t[m];
        }
      }
      if (consistent) p.q[i] = qscale * Q;  // with the returned plastic extensions
    });
  };
  with_form(prm, [&](auto paper_c, auto lps_c) {
    with_flag(prm.plastic, [&](auto plastic_c) { kernel(paper_c, plastic_c, lps_c); });
  });
}

namespace {

// The force pass: blocks of kBlock bonds (see the bond blocks above).

// Gathered per block: only what is indexed by the neighbour j (the per-bond arrays are read in
// place, contiguous from the block's first bond).
struct ForceBlock {
  alignas(64) Real ex[kBlock], ey[kBlock], ez[kBlock];  // u_j - u_i (eta - xi)
  alignas(64) Real xx[kBlock], xy[kBlock], xz[kBlock];  // xi = x0_j - x0_i
  alignas(64) Real dil_j[kBlock], b_j[kBlock], c_j[kBlock], crit_j[kBlock];
  alignas(64) Real pad0[kBlock], pad1[kBlock];  // the gathers' unused lanes
  alignas(64) Real fx[kBlock], fy[kBlock],
      fz[kBlock];                           // out: pair force density (0 for dead bonds)
  alignas(64) std::uint8_t broken[kBlock];  // out: eq. 18 holds (fracture)
};

// Per particle i: the terms of A_ij that depend on i only.
struct ForceRow {
  Real dil, b, c,
      crit;  // a theta - q; b; ed = e - c g (g = Lambda: paper, L: LPS); critical stretch
};

// What the force pass gathers per neighbour, in three 16-byte quads (gather_records).
struct alignas(16) ForceRec {
  Real y[4];   // displacement u (see displacement()), a theta - q
  Real x0[4];  // reference position, b
  Real cc[4];  // c, critical stretch, 0, 0
};

// The block's bonds k = kb .. kb + n - 1 of particle i (arrays offset by kb).
struct BondSlice {
  const Real *L, *omega, *shear, *vol, *epi, *omega_r, *shear_r, *epj;
  const std::uint8_t* live;
};

template <bool Paper, bool Fracture, bool Plastic, bool Lps>
void force_block(ForceBlock& B, const BondSlice& S, int n, const ForceRow& r, Real delta,
                 bool classical) {
  for (int m = 0; m < n; ++m) {  // vectorised: no branches, no gathers
    const Real epi = Plastic ? S.epi[m] : Real(0), epj = Plastic ? S.epj[m] : Real(0);
    const Real ex = B.xx[m] + B.ex[m], ey = B.xy[m] + B.ey[m], ez = B.xz[m] + B.ez[m];  // eta
    const Real l2 = ex * ex + ey * ey + ez * ez;
    const bool ok = (l2 > 0) & (S.live[m] != 0);  // coincident particles: no direction, no force
    const Real l = std::sqrt(ok ? l2 : Real(1));
    const Real L = S.L[m];
    const Real inv = Real(1) / (l * L);  // r = 1 / (l L): 1 / l = r L, Lambda = (eta . xi) r
    const Real e = l - L;
    const Real lambda = (ex * B.xx[m] + ey * B.xy[m] + ez * B.xz[m]) * inv;
    const Real g = Paper ? lambda : L;
    const Real gd = Lps ? L : lambda;  // the dilatational term's direction factor
    // eqs. 3, 7, 11 from each end of the bond (PdModel::Lps: 2 t_ij of Silling et al. 2007 eq. 4.5)
    const Real aij = Real(4) * (S.omega[m] * gd * r.dil + S.shear[m] * r.b * (e - r.c * g - epi));
    const Real aji = Real(4) * (S.omega_r[m] * gd * B.dil_j[m] +
                                S.shear_r[m] * B.b_j[m] * (e - B.c_j[m] * g - epj));
    // Dead bonds: times 0 (not a select, which would make the per-bond loads conditional and stop
    // the vectorisation); their operands are finite (l = 1 stands in when l2 = 0).
    const Real live = ok ? Real(1) : Real(0);
    const Real c =
        live * (Real(0.5) * (aij + aji) * S.vol[m] * (inv * L));  // eq. 1 with eq. 2, / l
    B.fx[m] = c * ex, B.fy[m] = c * ey, B.fz[m] = c * ez;
    if (Fracture) {  // eq. 18 (or the classical bond stretch), from both ends: symmetric
      const Real d = classical ? L : delta;
      B.broken[m] = ok & (((e - epi) / d > r.crit) | ((e - epj) / d > B.crit_j[m]));
    }
  }
}

// phi_i = 1 - n_i / N_i (eq. 18's damage) of row i; returns n_i.
inline std::uint64_t row_damage(const PdView& p, const PdBonds& bonds, std::size_t i) {
  std::int32_t c = 0;
  for (std::uint64_t k = bonds.offsets[i]; k < bonds.offsets[i + 1]; ++k) c += bonds.intact[k];
  p.damage[i] = p.bonds0[i] > 0 ? Real(1) - Real(c) / Real(p.bonds0[i]) : Real(0);
  return std::uint64_t(c);
}

}  // namespace

void pd_forces(const exec::Space& space, const PdView& p, PdBonds& bonds, const PdParams& prm,
               bool fracture, Vec3* force, Mat3* stress, PdScratch* scratch,
               std::uint64_t* intact) {
  const Real delta = prm.horizon;
  const bool paper = prm.model == PdModel::Paper && prm.deviatoric == PdDeviatoric::Paper;
  const bool classical = prm.criterion == PdCriterion::Classical;
  const PdMaterial* mats = prm.materials;
  const bool consistent = prm.consistent;
  // Per particle: the far end's terms and positions, gathered once per bond below (and a row's
  // own terms read back from its record).
  std::vector<Real> local;
  ForceRec* const recs = scratch_records<ForceRec>(scratch, local, p.n);
  exec::parallel_for(space, "pd.forces_rows", exec::Index(p.n), [&](exec::Index ii) {
    const std::size_t i = std::size_t(ii);
    const PdMaterial& mi = mats[p.material[i]];
    const Real ti = p.theta[i];
    const Real dil =
        p.a[i] * ti - (consistent ? p.q[i] : Real(0));  // a theta (- q: consistent term)
    const Real c = paper ? p.kappa[i] * ti : ti / Real(3);
    const Real crit = mi.critical_stretch * (Real(1) + mi.alpha * p.damage[i]);
    const Vec3 u = displacement(p, i);
    ::new (static_cast<void*>(recs + i)) ForceRec{
        {u[0], u[1], u[2], dil}, {p.x0[i][0], p.x0[i][1], p.x0[i][2], p.b[i]}, {c, crit, 0, 0}};
  });
  auto kernel = [&](auto paper_c, auto fracture_c, auto plastic_c, auto lps_c) {
    constexpr bool Paper = decltype(paper_c)::value, Fracture = decltype(fracture_c)::value;
    constexpr bool Plastic = decltype(plastic_c)::value, Lps = decltype(lps_c)::value;
    const std::uint64_t count = exec::parallel_reduce(
        space, "pd.forces", exec::Index(p.n), std::uint64_t(0),
        [&](exec::Index ii, std::uint64_t& acc) {
          const std::size_t i = std::size_t(ii);
          const std::uint64_t k0 = bonds.offsets[i], k1 = bonds.offsets[i + 1];
          const Real sub_y[4] = {recs[i].y[0], recs[i].y[1], recs[i].y[2], 0};
          const Real sub[3][4] = {{sub_y[0], sub_y[1], sub_y[2], 0},
                                  {p.x0[i][0], p.x0[i][1], p.x0[i][2], 0},
                                  {0, 0, 0, 0}};
          const ForceRec& own = recs[i];
          const ForceRow ri{own.y[3], own.x0[3], own.cc[0], own.cc[1]};
          const bool dense = bonds.dense[i] != 0;
          alignas(32) Real ax[kSumLanes] = {}, ay[kSumLanes] = {}, az[kSumLanes] = {};
          Mat3 s = Mat3::Zero();
          ForceBlock B;
          Real* const out[3][4] = {{B.ex, B.ey, B.ez, B.dil_j},
                                   {B.xx, B.xy, B.xz, B.b_j},
                                   {B.c_j, B.crit_j, B.pad0, B.pad1}};
          for (std::uint64_t kb = k0; kb < k1; kb += kBlock) {
            const int n = int(std::min<std::uint64_t>(kBlock, k1 - kb));
            const std::uint32_t* nb = bonds.neighbor.data() + kb;  // gather: eta, xi and j's terms
            gather_records<3, true>(recs, sizeof(ForceRec), nb, n, sub, out);
            const BondSlice S{bonds.length.data() + kb,        bonds.omega.data() + kb,
                              bonds.shear_omega.data() + kb,   bonds.volume.data() + kb,
                              bonds.plastic.data() + kb,       bonds.omega_r.data() + kb,
                              bonds.shear_omega_r.data() + kb, bonds.plastic_r.data() + kb,
                              bonds.intact.data() + kb};
            force_block<Paper, Fracture, Plastic, Lps>(B, S, n, ri, delta, classical);
            const std::uint8_t* lane = bonds.lane.data() + kb;
            lane_sum(B.fx, lane, dense, n, ax), lane_sum(B.fy, lane, dense, n, ay),
                lane_sum(B.fz, lane, dense, n, az);
            if (stress)  // sigma_i = 1/2 sum_j f_ij (x) xi V_j
              for (int m = 0; m < n; ++m)
                s += Real(0.5) * Vec3(B.fx[m], B.fy[m], B.fz[m]) *
                     Vec3(B.xx[m], B.xy[m], B.xz[m]).transpose();
            if (Fracture) {
              unsigned any = 0;  // vectorised OR first: bonds rarely break
              for (int m = 0; m < n; ++m) any |= B.broken[m];
              if (any)
                for (int m = 0; m < n; ++m)
                  if (B.broken[m]) bonds.intact[kb + std::uint64_t(m)] = 0;
            }
          }
          force[i] = Vec3(lane_total(ax), lane_total(ay), lane_total(az));
          if (stress) stress[i] = s;
          if (intact) acc += row_damage(p, bonds, i);  // after the row's fracture (pd_damage)
        },
        [](std::uint64_t a, std::uint64_t b) { return a + b; });
    if (intact) *intact = count;
  };
  with_form(prm, [&](auto paper_c, auto lps_c) {
    with_flag(fracture, [&](auto fracture_c) {
      with_flag(prm.plastic,
                [&](auto plastic_c) { kernel(paper_c, fracture_c, plastic_c, lps_c); });
    });
  });
}

void pd_build_contact_list(const exec::Space& space, const Vec3* x, std::size_t n, Real radius,
                           PdContactList& list) {
  list.x_built.assign(x, x + n);
  neighbour_rows(space, {"pd.contact_count", "pd.contact_scan", "pd.contact_fill"}, x, n, radius,
                 list.offsets, list.neighbor);
}

Real pd_max_displacement(const exec::Space& space, const Vec3* x, const PdContactList& list) {
  return exec::parallel_reduce(
      space, "pd.contact_check", exec::Index(list.x_built.size()), Real(0),
      [&](exec::Index i, Real& acc) {
        acc = std::max(acc, (x[i] - list.x_built[std::size_t(i)]).norm());
      },
      [](Real a, Real b) { return std::max(a, b); });
}

void pd_contact_forces(const exec::Space& space, const PdView& p, const PdBonds& bonds,
                       const PdParams& prm, Real distance, const PdContactList& list, Vec3* force) {
  if (p.n == 0 || !(distance > 0)) return;
  const double c0 = 15.0 * 18.0 / (M_PI * std::pow(double(prm.horizon), 4));
  const Real inv_delta = Real(1) / prm.horizon, d2 = distance * distance;
  exec::parallel_for(space, "pd.contact", exec::Index(p.n), [&](exec::Index ii) {
    const std::size_t i = std::size_t(ii);
    const std::uint32_t* row = bonds.neighbor.data() + bonds.offsets[i];
    const std::uint32_t* row_end = bonds.neighbor.data() + bonds.offsets[i + 1];
    const Real ki = prm.materials[p.material[i]].bulk;
    Vec3 f = Vec3::Zero();
    for (std::uint64_t c = list.offsets[i]; c < list.offsets[i + 1]; ++c) {
      const std::uint32_t j = list.neighbor[c];
      const Vec3 d = p.x[j] - p.x[i];
      const Real r2 = d.squaredNorm();
      if (!(r2 < d2) || !(r2 > 0)) continue;
      const std::uint32_t* b = std::lower_bound(row, row_end, j);
      Real dij = distance;
      if (b != row_end && *b == j) {
        const std::uint64_t k = bonds.offsets[i] + std::uint64_t(b - row);
        if (bonds.intact[k]) continue;  // bonded
        // A broken bond: contact below 0.9 of its reference length (LAMMPS's min(0.9 r0, d)),
        // so pairs that started closer than `distance` (tetrahedron barycentres) are not pushed
        // apart the moment their bond breaks.
        dij = pd_broken_pair_distance(bonds.length[k], distance);
        if (!(r2 < dij * dij)) continue;
      }
      const Real r = std::sqrt(r2);
      const Real cs = Real(c0 * 0.5 * double(ki + prm.materials[p.material[j]].bulk));
      f -= (cs * (dij - r) * inv_delta * p.volume[j] / r) * d;
    }
    force[i] += f;
  });
}

std::uint64_t pd_damage(const exec::Space& space, const PdView& p, const PdBonds& bonds) {
  return exec::parallel_reduce(
      space, "pd.damage", exec::Index(p.n), std::uint64_t(0),
      [&](exec::Index i, std::uint64_t& acc) { acc += row_damage(p, bonds, std::size_t(i)); },
      [](std::uint64_t a, std::uint64_t b) { return a + b; });
}

namespace {

// A bond list of the layout `offsets`, its copied per-bond arrays sized (copy_bond fills them).
PdBonds sized_bonds(const std::vector<std::uint64_t>& offsets) {
  const std::uint64_t total = offsets.back();
  PdBonds out;
  out.offsets = offsets;
  out.neighbor.resize(total);
  out.length.resize(total);
  out.omega.resize(total);
  out.shear_omega.resize(total);
  out.volume.resize(total);
  out.plastic.resize(total);
  out.intact.resize(total);
  out.lane.resize(total);
  out.dense.resize(offsets.size() - 1);
  return out;
}

// Bond k of `from` into slot o of `to` (the per-bond arrays that are not rebuilt afterwards).
inline void copy_bond(const PdBonds& from, std::uint64_t k, PdBonds& to, std::uint64_t o) {
  to.neighbor[o] = from.neighbor[k];
  to.length[o] = from.length[k];
  to.omega[o] = from.omega[k];
  to.shear_omega[o] = from.shear_omega[k];
  to.volume[o] = from.volume[k];
  to.plastic[o] = from.plastic[k];
  to.intact[o] = from.intact[k];
  to.lane[o] = from.lane[k];
}

// Keeps the bonds with keep[k] != 0 (rows keep their order, every per-bond array is copied,
// reverse indices rebuilt). Returns the number removed.
std::uint64_t select_bonds(const exec::Space& space, const char* label_copy, PdBonds& bonds,
                           const std::vector<std::uint8_t>& keep) {
  const std::size_t n = bonds.particles();
  std::vector<std::uint64_t> count(n), off(n + 1);
  exec::parallel_for(space, "pd.compact_count", exec::Index(n), [&](exec::Index i) {
    std::uint64_t c = 0;
    for (std::uint64_t k = bonds.offsets[std::size_t(i)]; k < bonds.offsets[std::size_t(i) + 1];
         ++k)
      c += keep[k] != 0;
    count[std::size_t(i)] = c;
  });
  const std::uint64_t total = exec::parallel_scan<std::uint64_t>(
      space, "pd.compact_scan", exec::Index(n),
      [&](exec::Index i) { return count[std::size_t(i)]; }, off.data());
  off[n] = total;
  const std::uint64_t removed = bonds.size() - total;
  if (removed == 0) return 0;
  PdBonds out = sized_bonds(off);
  exec::parallel_for(space, label_copy, exec::Index(n), [&](exec::Index ii) {
    const std::size_t i = std::size_t(ii);
    std::uint64_t o = off[i];
    for (std::uint64_t k = bonds.offsets[i]; k < bonds.offsets[i + 1]; ++k) {
      if (!keep[k]) continue;
      copy_bond(bonds, k, out, o++);
    }
    out.dense[i] = bonds.dense[i] && o - off[i] == bonds.offsets[i + 1] - bonds.offsets[i];
  });
  fill_reverse(space, "pd.compact_reverse", out.offsets, out.neighbor, out.reverse);
  bonds = std::move(out);
  pd_mirror_bonds(space, bonds);
  return removed;
}

}  // namespace

void pd_keep_rows(const exec::Space& space, PdBonds& bonds,
                  const std::vector<std::uint8_t>& keep_row) {
  const std::size_t n = bonds.particles();
  std::vector<std::uint64_t> off(n + 1, 0);
  for (std::size_t i = 0; i < n; ++i)
    off[i + 1] = off[i] + (keep_row[i] ? bonds.offsets[i + 1] - bonds.offsets[i] : 0);
  const std::uint64_t total = off[n];
  PdBonds out = sized_bonds(off);
  out.reverse.resize(total);  // and the mirrored arrays, copied rather than rebuilt
  out.omega_r.resize(total);
  out.shear_omega_r.resize(total);
  out.plastic_r.resize(total);
  exec::parallel_for(space, "pd.keep_rows", exec::Index(n), [&](exec::Index ii) {
    const std::size_t i = std::size_t(ii);
    out.dense[i] = keep_row[i] ? bonds.dense[i] : 1;  // an empty row is trivially whole
    if (!keep_row[i]) return;
    std::uint64_t o = off[i];
    for (std::uint64_t k = bonds.offsets[i]; k < bonds.offsets[i + 1]; ++k, ++o) {
      const std::uint32_t j = bonds.neighbor[k];
      copy_bond(bonds, k, out, o);
      // The reverse bond keeps its position within row j.
      out.reverse[o] = keep_row[j] ? off[j] + (bonds.reverse[k] - bonds.offsets[j]) : kNoReverse;
      out.omega_r[o] = bonds.omega_r[k];
      out.shear_omega_r[o] = bonds.shear_omega_r[k];
      out.plastic_r[o] = bonds.plastic_r[k];
    }
  });
  bonds = std::move(out);
}

std::uint64_t pd_compact_bonds(const exec::Space& space, PdBonds& bonds, Real contact_distance) {
  std::vector<std::uint8_t> keep(bonds.size());
  exec::parallel_for(space, "pd.compact_mark", exec::Index(bonds.size()), [&](exec::Index k) {
    keep[std::size_t(k)] =
        bonds.intact[std::size_t(k)] ||
        pd_contact_reads_broken_bond(bonds.length[std::size_t(k)], contact_distance);
  });
  return select_bonds(space, "pd.compact_copy", bonds, keep);
}

bool pd_restrict_bonds(const exec::Space& space, PdBonds& bonds,
                       const std::vector<std::uint64_t>& offsets,
                       const std::vector<std::uint32_t>& neighbor) {
  const std::size_t n = bonds.particles();
  if (offsets.size() != n + 1 || offsets[0] != 0 || offsets[n] != neighbor.size()) return false;
  for (std::size_t i = 0; i < n; ++i)
    if (offsets[i] > offsets[i + 1]) return false;
  std::vector<std::uint8_t> keep(bonds.size(), 0);
  // Row by row, a merge of the sorted rows: every given neighbour must be in the full row.
  const std::uint64_t bad = exec::parallel_reduce(
      space, "pd.restrict_mark", exec::Index(n), std::uint64_t(0),
      [&](exec::Index ii, std::uint64_t& acc) {
        const std::size_t i = std::size_t(ii);
        std::uint64_t k = bonds.offsets[i];
        const std::uint64_t k1 = bonds.offsets[i + 1];
        for (std::uint64_t c = offsets[i]; c < offsets[i + 1]; ++c) {
          while (k < k1 && bonds.neighbor[k] < neighbor[c]) ++k;
          if (k == k1 || bonds.neighbor[k] != neighbor[c]) {
            ++acc;
            return;
          }
          keep[k++] = 1;
        }
      },
      [](std::uint64_t a, std::uint64_t b) { return a + b; });
  if (bad) return false;
  select_bonds(space, "pd.restrict_copy", bonds, keep);
  return true;
}

}  // namespace amalgam
