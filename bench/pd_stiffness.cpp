// Diagnostic (not built by CMake, not in CI): the linearised peridynamic stiffness of a small
// (optionally notched) simple-cubic body, assembled by central finite differences of
// pd_dilatation + pd_forces about a homogeneously stretched state; reports its asymmetry
// |K - K^T| / |K| and the eigenvalues of M^-1 K (flutter: complex pairs; divergence: negative
// real parts) with the particles carrying the fastest-growing mode. Not built by CMake; against a
// double-precision build (cmake -DAMALGAM_REAL=double -B build-double, target amalgam_kernels):
//   g++ -O2 -std=c++17 -DAMALGAM_REAL_DOUBLE=1 -fopenmp -I. -isystem /usr/include/eigen3
//     bench/pd_stiffness.cpp <the libraries of
//     build-double/bench/CMakeFiles/amalgam_pd_notch.dir/link.txt> -o pd_stiffness
//   pd_stiffness [--nx 12 --ny 6 --nz 6 --notch 2 --corr 1 --consistent (= corr) --form paper|lps
//                 --eps 0 --epsy 0 (homogeneous stretch) --h 1e-6 (step, in lc) --worst 8]
// Measured (docs/validation.md): 12 x 6 x 6 with a notch, corrected, at rest: symmetric to the
// differences' error (4e-11), no growing mode; stretched by 2e-3: asymmetry 2e-7, the fastest
// growth 0.12 / s (a near-rigid mode), against the 1e6 / s of the bar's former mirror mode.
#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"
#include "kernels/peridynamics.hpp"
using namespace amalgam;

int main(int argc, char** argv) {
  int nx = 12, ny = 6, nz = 6, notch = 2, corr = 1, consistent = -1, worst = 8;
  double eps = 0, epsy = 0, lc = 0.01, h = 1e-6;
  std::string form = "paper";
  for (int i = 1; i + 1 < argc; i += 2) {
    std::string a = argv[i];
    const char* v = argv[i + 1];
    if (a == "--nx")
      nx = atoi(v);
    else if (a == "--ny")
      ny = atoi(v);
    else if (a == "--nz")
      nz = atoi(v);
    else if (a == "--notch")
      notch = atoi(v);
    else if (a == "--corr")
      corr = atoi(v);
    else if (a == "--consistent")
      consistent = atoi(v);
    else if (a == "--form")
      form = v;
    else if (a == "--eps")
      eps = atof(v);
    else if (a == "--epsy")
      epsy = atof(v);
    else if (a == "--h")
      h = atof(v);
    else if (a == "--worst")
      worst = atoi(v);
    else {
      fprintf(stderr, "unknown %s\n", a.c_str());
      return 2;
    }
  }
  if (consistent < 0) consistent = corr;
  const exec::Space space(exec::Backend::Serial, 1);
  std::vector<Vec3> x0;
  std::vector<Eigen::Vector3i> ijk;
  for (int a = 0; a < nx; ++a)
    for (int b = 0; b < ny; ++b)
      for (int c = 0; c < nz; ++c) {
        if (notch > 0 && (a == nx / 2 - 1 || a == nx / 2) && b >= ny - notch) continue;
        x0.push_back(
            Vec3(lc * (a - 0.5 * (nx - 1)), lc * (b - 0.5 * (ny - 1)), lc * (c - 0.5 * (nz - 1))));
        ijk.push_back(Eigen::Vector3i(a, b, c));
      }
  const std::size_t n = x0.size();
  PdMaterial glass;
  glass.bulk = 48e9, glass.shear = 28.8e9, glass.density = 2200;
  PdParams prm;
  prm.horizon = 3.015 * lc, prm.spacing = lc;
  prm.deviatoric = form == "paper" ? PdDeviatoric::Paper : PdDeviatoric::Lps;
  prm.materials = &glass;
  prm.consistent = consistent;
  prm.plastic = false;
  std::vector<Real> vol(n, lc * lc * lc), theta(n), q(n), dmg(n, 0);
  std::vector<std::int32_t> mat(n, 0);
  PdBonds bonds;
  pd_build_bonds(space, x0.data(), vol.data(), mat.data(), n, prm, true, bonds);
  PdConstants C;
  pd_constants(space, x0.data(), mat.data(), bonds, prm, corr, C);
  int nf[3] = {0, 0, 0};
  double amin = 1e300, amax = -1e300;
  for (std::size_t i = 0; i < n; ++i)
    ++nf[C.fitted[i]], amin = std::min(amin, C.a[i]), amax = std::max(amax, C.a[i]);
  printf("# n %zu bonds %zu fitted 0/1/2: %d %d %d  a min %.4g max %.4g (continuum %.4g)\n", n,
         bonds.size(), nf[0], nf[1], nf[2], amin, amax,
         1.5 * 48e9 / (4 * M_PI * std::pow(prm.horizon, 4) / 3));
  std::vector<Vec3> x(n), f(n), fp(n), fm(n);
  for (std::size_t i = 0; i < n; ++i)
    x[i] = Vec3(x0[i][0] * (1 + eps), x0[i][1] * (1 + epsy), x0[i][2]);
  PdView p;
  p.n = n, p.x0 = x0.data(), p.x = x.data(), p.volume = vol.data(), p.material = mat.data();
  p.theta = theta.data(), p.q = q.data(), p.damage = dmg.data(), p.m = C.m.data(), p.a = C.a.data(),
  p.b = C.b.data(), p.kappa = C.kappa.data(), p.bonds0 = C.bonds0.data();
  auto force = [&](std::vector<Vec3>& out) {
    pd_dilatation(space, p, bonds, prm);
    pd_forces(space, p, bonds, prm, false, out.data(), nullptr);
  };
  const std::size_t N = 3 * n;
  Eigen::MatrixXd K(N, N);
  const double du = h * lc;
  for (std::size_t b = 0; b < n; ++b)
    for (int d = 0; d < 3; ++d) {
      const Real keep = x[b][d];
      x[b][d] = keep + du;
      force(fp);
      x[b][d] = keep - du;
      force(fm);
      x[b][d] = keep;
      for (std::size_t a = 0; a < n; ++a)
        for (int e = 0; e < 3; ++e)  // K = -dF/du, F = f V (force, N)
          K(3 * a + e, 3 * b + d) = -(fp[a][e] - fm[a][e]) * vol[a] / (2 * du);
    }
  const double kn = K.norm();
  const Eigen::MatrixXd A = K - K.transpose();
  printf("# |K| %.4e  |K-K^T|/|K| %.4e  max|K-K^T|/max|K| %.4e\n", kn, A.norm() / kn,
         A.cwiseAbs().maxCoeff() / K.cwiseAbs().maxCoeff());
  // Where the asymmetry lives: per particle row sum of |A|^2.
  {
    std::vector<std::pair<double, std::size_t>> r(n);
    for (std::size_t a = 0; a < n; ++a) r[a] = {A.middleRows(3 * a, 3).norm(), a};
    std::sort(r.rbegin(), r.rend());
    printf("# largest asymmetric rows (|A row| / |K|, ijk, fitted):\n");
    for (int k = 0; k < std::min<int>(worst, int(n)); ++k)
      printf("#   %.3e  (%d %d %d) fitted %d\n", r[k].first / kn, ijk[r[k].second][0],
             ijk[r[k].second][1], ijk[r[k].second][2], C.fitted[r[k].second]);
  }
  // Mass-normalised: M^-1 K, M = rho V (uniform): omega^2 = eig / (rho V).
  const double mass = glass.density * lc * lc * lc;
  Eigen::EigenSolver<Eigen::MatrixXd> es(K / mass);
  const Eigen::VectorXcd ev = es.eigenvalues();
  double remin = 1e300, remax = -1e300, immax = 0;
  for (int k = 0; k < int(N); ++k) {
    remin = std::min(remin, ev[k].real());
    remax = std::max(remax, ev[k].real());
    immax = std::max(immax, std::abs(ev[k].imag()));
  }
  // Growth rate of x'' = -lambda x: Re sqrt(-lambda)
  auto growth = [](std::complex<double> l) { return std::sqrt(-l).real(); };
  double gmax = 0;
  int ig = 0;
  for (int k = 0; k < int(N); ++k)
    if (std::abs(growth(ev[k])) > gmax) gmax = std::abs(growth(ev[k])), ig = k;
  printf("# eig(M^-1 K): max Re %.4e (omega_max %.4e rad/s)  min Re %.4e  max |Im| %.4e\n", remax,
         std::sqrt(remax), remin, immax);
  printf("# largest growth rate %.4e 1/s at lambda = %.4e %+.4ei\n", gmax, ev[ig].real(),
         ev[ig].imag());
  const Eigen::VectorXcd vec = es.eigenvectors().col(ig);
  std::vector<std::pair<double, std::size_t>> r(n);
  for (std::size_t a = 0; a < n; ++a) r[a] = {vec.segment(3 * a, 3).norm(), a};
  std::sort(r.rbegin(), r.rend());
  printf("# worst mode's largest particles (|v|, ijk, fitted):\n");
  for (int k = 0; k < std::min<int>(worst, int(n)); ++k)
    printf("#   %.3e  (%d %d %d) fitted %d\n", r[k].first, ijk[r[k].second][0], ijk[r[k].second][1],
           ijk[r[k].second][2], C.fitted[r[k].second]);
  // Sorted growth rates (the top few).
  std::vector<double> g(N);
  for (int k = 0; k < int(N); ++k) g[k] = growth(ev[k]);
  std::sort(g.rbegin(), g.rend());
  printf("# top growth rates:");
  for (int k = 0; k < 12; ++k) printf(" %.3e", g[k]);
  printf("\n");
}
