// Notched glass bar (or an unnotched block) on a simple-cubic lattice, peridynamics after
// fracture (docs/validation.md, "Peridynamics after fracture"): prints per interval the broken
// bonds, kinetic energy, largest speed, the damage sums of the two halves and the largest mirror
// difference of positions (in lattice spacings) and velocities (in end speeds), with the lattice
// indices of the particle where the position difference is largest and that particle's
// displacement (in lattice spacings): a difference that stays a fixed fraction of the local
// displacement is an asymmetric model, not a growing mode (docs/validation.md). The lattice is
// centred on x = 0, so the mirror is exact in float (--shift moves it away from the origin). The
// LAMMPS peri/lps peer of the same bar is bench/pd_notch.lmp.
//
//   amalgam_pd_notch [--nx 60 --ny 10 --nz 10 --notch 3 --endlayers 1 --vend 12] [--s00 1e-3]
//                    [--crit classical|paper] [--model paper|lps] [--form paper|lps] [--corr 1]
//                    [--contact 1] [--cd 0.9 (contact distance / lc; LAMMPS: 1.35)]
//                    [--fracture 1] [--dtf 1 | --dt SECONDS] [--tend 2e-3] [--every 1e-4]
//                    [--vprof ends|linear] [--shift 0] [--threads 2]
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>
#include "core/exec/exec.hpp"
#include "solvers/pd_solver.hpp"
using namespace amalgam;

int main(int argc, char** argv) {
  int nx = 60, ny = 10, nz = 10, notch = 3, endl = 1, threads = 2, fracture = 1, contact = 1,
      corr = 1;
  double lc = 0.01, dtf = 1.0, dt_abs = 0, tend = 2e-3, every = 1e-4, vend = 12, s00 = 1e-3,
         cd = 0.9;
  double shift = 0;  // lattice origin shift (0: centred, mirror exact)
  std::string crit = "classical", form = "paper", mode = "notch", vprof = "ends", model = "paper";
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
    else if (a == "--endlayers")
      endl = atoi(v);
    else if (a == "--threads")
      threads = atoi(v);
    else if (a == "--fracture")
      fracture = atoi(v);
    else if (a == "--contact")
      contact = atoi(v);
    else if (a == "--corr")
      corr = atoi(v);
    else if (a == "--lc")
      lc = atof(v);
    else if (a == "--dtf")
      dtf = atof(v);
    else if (a == "--dt")
      dt_abs = atof(v);
    else if (a == "--tend")
      tend = atof(v);
    else if (a == "--every")
      every = atof(v);
    else if (a == "--vend")
      vend = atof(v);
    else if (a == "--s00")
      s00 = atof(v);
    else if (a == "--cd")
      cd = atof(v);
    else if (a == "--shift")
      shift = atof(v);
    else if (a == "--crit")
      crit = v;
    else if (a == "--form")
      form = v;
    else if (a == "--model")
      model = v;
    else if (a == "--vprof")
      vprof = v;
    else {
      fprintf(stderr, "unknown %s\n", a.c_str());
      return 2;
    }
  }
  const exec::Space space(exec::parse_backend("openmp"), threads);
  PdSettings s;
  s.spacing = Real(lc);
  s.horizon = Real(3.015 * lc);
  s.model = model == "lps" ? PdModel::Lps : PdModel::Paper;
  s.deviatoric = form == "paper" && model != "lps" ? PdDeviatoric::Paper : PdDeviatoric::Lps;
  s.surface_correction = corr && model != "lps";
  s.partial_volume = true;
  s.fracture = fracture;
  s.criterion = crit == "classical" ? PdCriterion::Classical : PdCriterion::Paper;
  s.contact = contact;
  s.contact_distance = Real(cd * lc);
  s.gravity = Vec3::Zero();
  s.compact_fraction = 0;
  PdMaterial glass;
  glass.bulk = Real(48e9);
  glass.shear = Real(28.8e9);
  glass.density = 2200;
  if (fracture) glass.critical_stretch = Real(s00);
  PdSolver solver(s, {glass});
  std::vector<Vec3> x;
  std::vector<int> ia, ib, ic;
  std::vector<long> idx(size_t(nx) * ny * nz, -1);
  for (int a = 0; a < nx; ++a)
    for (int b = 0; b < ny; ++b)
      for (int c = 0; c < nz; ++c) {
        bool cut = notch > 0 && (a == nx / 2 - 1 || a == nx / 2) && b >= ny - notch;
        if (cut) continue;
        idx[(size_t(a) * ny + b) * nz + c] = long(x.size());
        x.push_back(Vec3(Real(lc * (a - 0.5 * (nx - 1)) + shift), Real(lc * (b - 0.5 * (ny - 1))),
                         Real(lc * (c - 0.5 * (nz - 1)))));
        ia.push_back(a), ib.push_back(b), ic.push_back(c);
      }
  std::vector<long> mir(x.size());
  for (int a = 0; a < nx; ++a)
    for (int b = 0; b < ny; ++b)
      for (int c = 0; c < nz; ++c) {
        long i = idx[(size_t(a) * ny + b) * nz + c];
        if (i < 0) continue;
        mir[i] = idx[(size_t(nx - 1 - a) * ny + b) * nz + c];
      }
  solver.add_particles(x, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0, Real(lc * lc * lc));
  solver.initialize(space);
  Vec3* v = solver.particles().vec3(solver.attributes().v);
  for (size_t i = 0; i < x.size(); ++i) {
    if (vprof == "ends") {
      if (ia[i] < endl) v[i] = Vec3(Real(-vend), 0, 0);
      if (ia[i] >= nx - endl) v[i] = Vec3(Real(vend), 0, 0);
    } else if (vprof == "linear") {  // v = vend * x / (L/2)
      v[i] = Vec3(Real(vend * (ia[i] - 0.5 * (nx - 1)) / (0.5 * (nx - 1))), 0, 0);
    }
  }
  const Real dt0 = dt_abs > 0 ? Real(dt_abs) : Real(dtf) * solver.stable_dt(space);
  const Vec3* px = solver.particles().vec3(solver.attributes().x);
  const Real* dmg = solver.particles().real(solver.attributes().damage);
  printf("# particles %zu bonds %zu dt %.4g\n", x.size(), solver.bonds().size(), double(dt0));
  // dmgL, dmgR: damage sums of the two halves; with equal particle volumes the same quantity as
  // LAMMPS's compute damage/atom (1 - intact share of the family's volumes vfrac_j), so the
  // columns compare directly with bench/pd_notch.lmp's c_dl c_dr. Positions are x + x_lo.
  printf(
      "# t_ms broken KE_J vmax vmax_x0 vmax_y0 dmgL dmgR mirr_x_rel mirr_v_rel at_i at_j at_k u_at_rel\n");
  const Vec3* plo = solver.particles().vec3(solver.attributes().x_lo);
  auto pos = [&](size_t i) { return Vec3d(px[i].cast<double>() + plo[i].cast<double>()); };
  const long nsteps = long(std::ceil(tend / dt0)),
             pe = std::max(1L, long(std::llround(every / dt0)));
  double worst = 0;
  for (long st = 0; st <= nsteps; ++st) {
    if (st > 0) solver.step(space, dt0);
    if (st % pe != 0 && st != nsteps) continue;
    PdDiagnostics d = solver.diagnostics(space);
    double dl = 0, dr = 0, ax = 0, av = 0, vm = 0;
    size_t im = 0, iw = 0;
    for (size_t i = 0; i < x.size(); ++i) {
      (ia[i] < nx / 2 ? dl : dr) += dmg[i];
      double sp = v[i].cast<double>().norm();
      if (sp > vm) vm = sp, im = i;
      size_t j = size_t(mir[i]);
      const Vec3d pj = pos(j);
      const Vec3d mx(-pj[0] + 2 * shift, pj[1], pj[2]);
      const double dx = (pos(i) - mx).norm();
      if (dx > ax) ax = dx, iw = i;
      Vec3d mv(-double(v[j][0]), v[j][1], v[j][2]);
      av = std::max(av, (v[i].cast<double>() - mv).norm());
    }
    worst = std::max(worst, ax);
    printf("%.4f %llu %.4g %.4g %.3f %.3f %.3f %.3f %.3e %.3e %d %d %d %.3e\n", solver.time() * 1e3,
           (unsigned long long)(d.bonds - d.intact), d.kinetic, vm, double(x[im][0]),
           double(x[im][1]), dl, dr, ax / lc, av / std::max(vend, 1e-30), ia[iw], ib[iw], ic[iw],
           (pos(iw) - x[iw].cast<double>()).norm() / lc);
    fflush(stdout);
  }
  printf("# worst mirror |dx|/lc %.3e\n", worst / lc);
}
