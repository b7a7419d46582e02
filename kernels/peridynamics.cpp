#include "kernels/peridynamics.hpp"

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <type_traits>
#include <unordered_map>

#include <Eigen/QR>

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

// CSR rows of the particles' neighbours within r (rows sorted by index): a count pass, a scan
// and a fill pass over the cells. Row q is particle rows[q] (rows null: q, m = n); neighbours are
// indices into x. `what` prefixes the profiler labels.
struct RowLabels {
  const char *count, *scan, *fill;
};
void neighbour_rows(const exec::Space& space, const RowLabels& label, const Vec3* x, std::size_t n,
                    Real r, std::vector<std::uint64_t>& offsets,
                    std::vector<std::uint32_t>& neighbor, const std::uint32_t* rows = nullptr,
                    std::size_t m = 0) {
  if (!rows) m = n;
  offsets.assign(m + 1, 0);
  neighbor.clear();
  if (n == 0 || m == 0) return;
  const CellIndex cells = make_cells(space, x, n, double(r));
  std::vector<std::uint64_t> count(m);
  exec::parallel_for(space, label.count, exec::Index(m), [&](exec::Index q) {
    std::uint64_t c = 0;
    const std::uint32_t i = rows ? rows[q] : std::uint32_t(q);
    for_neighbours(cells, x, i, r, [&](std::uint32_t) { ++c; });
    count[std::size_t(q)] = c;
  });
  const std::uint64_t total = exec::parallel_scan<std::uint64_t>(
      space, label.scan, exec::Index(m), [&](exec::Index q) { return count[std::size_t(q)]; },
      offsets.data());
  offsets[m] = total;
  neighbor.resize(total);
  exec::parallel_for(space, label.fill, exec::Index(m), [&](exec::Index q) {
    std::uint32_t* row = neighbor.data() + offsets[std::size_t(q)];
    std::uint64_t c = 0;
    const std::uint32_t i = rows ? rows[q] : std::uint32_t(q);
    for_neighbours(cells, x, i, r, [&](std::uint32_t j) { row[c++] = j; });
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

void pd_build_bond_rows(const exec::Space& space, const Vec3* x0, const Real* volume,
                        const std::int32_t* material, std::size_t n, const std::uint32_t* rows,
                        std::size_t m, const PdParams& prm, bool partial_volume, PdBonds& bonds) {
  const Real delta = prm.horizon, lc = prm.spacing;
  neighbour_rows(space, {"pd.bond_count", "pd.bond_scan", "pd.bond_fill"}, x0, n, delta,
                 bonds.offsets, bonds.neighbor, rows, m);
  if (!rows) m = n;
  const std::size_t total = bonds.neighbor.size();
  bonds.length.resize(total);
  bonds.omega.resize(total);
  bonds.volume.resize(total);
  bonds.plastic.assign(total, Real(0));
  bonds.intact.assign(total, 1);
  bonds.lane.resize(total);
  bonds.dense.assign(m, 1);
  const std::uint64_t* off = bonds.offsets.data();
  exec::parallel_for(space, "pd.bond_geometry", exec::Index(m), [&](exec::Index q) {
    const std::size_t i = rows ? rows[q] : std::size_t(q);
    const Mat3& G = prm.materials[material[i]].G;
    for (std::uint64_t k = off[q]; k < off[q + 1]; ++k) {
      const std::uint32_t j = bonds.neighbor[k];
      const Vec3 xi = x0[j] - x0[i];
      const Real L = xi.norm();
      bonds.length[k] = L;
      bonds.omega[k] = delta / (G * xi).norm();  // eq. 16 (eq. 4 when G = I)
      Real nu = 1;
      if (partial_volume && L > delta - lc / 2) nu = std::min(Real(1), (delta + lc / 2 - L) / lc);
      bonds.volume[k] = nu * volume[j];
      bonds.lane[k] = std::uint8_t((k - off[q]) % kSumLanes);
    }
  });
  if (rows) bonds.reverse.assign(total, kNoReverse);
}

void pd_build_bonds(const exec::Space& space, const Vec3* x0, const Real* volume,
                    const std::int32_t* material, std::size_t n, const PdParams& prm,
                    bool partial_volume, PdBonds& bonds) {
  pd_build_bond_rows(space, x0, volume, material, n, nullptr, 0, prm, partial_volume, bonds);
  fill_reverse(space, "pd.bond_reverse", bonds.offsets, bonds.neighbor, bonds.reverse);
}

std::vector<std::uint64_t> pd_count_bonds(const exec::Space& space, const Vec3* x0, std::size_t n,
                                          const std::uint32_t* rows, std::size_t m, Real horizon) {
  std::vector<std::uint64_t> count(m);
  if (n == 0 || m == 0) return count;
  const CellIndex cells = make_cells(space, x0, n, double(horizon));
  exec::parallel_for(space, "pd.bond_count", exec::Index(m), [&](exec::Index q) {
    std::uint64_t c = 0;
    for_neighbours(cells, x0, rows[q], horizon, [&](std::uint32_t) { ++c; });
    count[std::size_t(q)] = c;
  });
  return count;
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

namespace {
// A family's signature (see pd_constants): material, row length, bond vectors and volumes to
// 1e-6 of delta and of the largest volume vmax. Row q is particle pi.
std::vector<std::int64_t> family_signature(const Vec3* x0, const std::int32_t* material,
                                           const PdBonds& bonds, std::size_t q, std::size_t pi,
                                           double delta, double vmax) {
  std::vector<std::int64_t> sig{std::int64_t(material[pi]),
                                std::int64_t(bonds.offsets[q + 1] - bonds.offsets[q])};
  for (std::uint64_t k = bonds.offsets[q]; k < bonds.offsets[q + 1]; ++k) {
    const Vec3d xi = (x0[bonds.neighbor[k]] - x0[pi]).cast<double>() / (1e-6 * delta);
    for (int a = 0; a < 3; ++a) sig.push_back(std::llround(xi[a]));
    sig.push_back(std::llround(double(bonds.volume[k]) / (1e-6 * vmax + 1e-300)));
  }
  return sig;
}
double largest_bond_volume(const PdBonds& bonds, const PdRowSubset* subset) {
  if (subset && subset->vmax >= 0) return subset->vmax;
  double vmax = 0;
  for (std::size_t k = 0; k < bonds.size(); ++k) vmax = std::max(vmax, double(bonds.volume[k]));
  return vmax;
}
}  // namespace

std::vector<std::uint64_t> pd_family_keys(const exec::Space& space, const Vec3* x0,
                                          const std::int32_t* material, const PdBonds& bonds,
                                          const PdParams& prm, const PdRowSubset* subset) {
  const std::size_t n = bonds.particles();
  const double delta = double(prm.horizon), vmax = largest_bond_volume(bonds, subset);
  const std::uint32_t* rows = subset ? subset->particle : nullptr;
  std::vector<std::uint64_t> key(n);
  exec::parallel_for(space, "pd.constants_keys", exec::Index(n), [&](exec::Index ii) {
    const std::size_t q = std::size_t(ii);
    const std::vector<std::int64_t> sig =
        family_signature(x0, material, bonds, q, rows ? rows[q] : q, delta, vmax);
    std::uint64_t h = 1469598103934665603ull;  // FNV-1a over the signature
    for (std::int64_t v : sig)
      for (int b = 0; b < 8; ++b)
        h = (h ^ ((std::uint64_t(v) >> (8 * b)) & 0xff)) * 1099511628211ull;
    key[q] = h;
  });
  return key;
}

std::size_t pd_constants(const exec::Space& space, const Vec3* x0, const std::int32_t* material,
                         PdBonds& bonds, const PdParams& prm, bool surface_correction,
                         PdConstants& out, const PdRowSubset* subset) {
  const std::size_t n = bonds.particles();
  const std::uint32_t* rows = subset ? subset->particle : nullptr;
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
  const double vmax = largest_bond_volume(bonds, subset);
  auto signature = [&](std::size_t q) {
    return family_signature(x0, material, bonds, q, rows ? rows[q] : q, delta, vmax);
  };
  const std::vector<std::uint64_t> key =
      subset && subset->key ? std::vector<std::uint64_t>(subset->key, subset->key + n)
                            : pd_family_keys(space, x0, material, bonds, prm, subset);
  const std::uint8_t* given = subset ? subset->given : nullptr;
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
    if (rep[i] != i) return;                    // copied from its representative below
    if (given && given[i]) return;              // fitted on another rank, set by subset->exchange
    const std::size_t pi = rows ? rows[i] : i;  // the row's particle
    const std::uint64_t k0 = bonds.offsets[i], k1 = bonds.offsets[i + 1];
    double m = m_cont, kappa = delta / 4;
    std::uint8_t fitted = 0;
    const PdMaterial& mat = prm.materials[material[pi]];
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
        const Vec3d xi = (x0[bonds.neighbor[k]] - x0[pi]).cast<double>();
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
  if (given && subset->exchange) subset->exchange(out, bonds);
  std::size_t fits = 0;
  for (std::size_t i = 0; i < n; ++i) fits += rep[i] == i && !(given && given[i]);
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
  if (!subset) pd_mirror_bonds(space, bonds);
  return fits;
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
