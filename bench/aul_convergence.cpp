// A-ULMPM spatial convergence (paper Sec. 6.1.1, Fig. 14) on a smooth problem with an exact
// solution: the free-free longitudinal standing wave of a bar (Poisson ratio 0, fixed-corotated,
// which is exactly linear in uniaxial stretch: P = E (F11 - 1)), carried by a rigid translation
// V so that particles cross cells:
//   u(X, t) = V t + A sin(w t) cos(k X'),  k = pi / L, w = k sqrt(E / rho),  X' = X - x_min.
// For each grid spacing dx (8 particles per cell, so particles refine with the grid) and each
// configuration policy, the run goes to t_end with the same dt for every dx (the finest grid's
// CFL step), and the error is the RMS over particles of |u_h - u| / A (displacement) and
// |v_h - v| / (A w) (velocity, exact at t - dt/2: leapfrog), the paper's eq. 36 against the exact field instead of a finest
// run. The order is the least-squares slope of log E vs log dx over the finest `--fit` spacings.
//
//   amalgam_aul_convergence [--levels 5] [--fit 3] [--csv FILE] [--png FILE]
//                           [--check ORDER] [--backend openmp --threads 2]
// --check ORDER runs only the total-Lagrangian MLS variant and exits 1 unless its displacement and
// velocity orders are both at least ORDER (ctest runs it on 3 levels).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"
#include "io/plot.hpp"
#include "io/preview.hpp"
#include "io/scene.hpp"
#include "solvers/factory.hpp"
#include "solvers/mpm_aul.hpp"
#include "solvers/mpm_enriched.hpp"
#include "solvers/mpm_implicit.hpp"

using namespace amalgam;

namespace {

constexpr double kL = 0.32, kW = 0.04, kE = 1e4, kRho = 1000, kA = 0.004, kV = 1.0, kXmin = 0.3;

struct Options {
  int levels = 5, fit = 3;
  std::string csv, png, backend = "openmp";
  int threads = 2;
  double check = 0;
};

struct Variant {
  std::string label, update, transfer;
};

struct Result {
  double dx = 0, disp = 0, vel = 0;
  std::uint64_t resets = 0;
};

Result run(const Variant& var, double dx, double dt, double t_end, const exec::Space& space) {
  char text[2048];
  std::snprintf(text, sizeof text, R"({
    "simulation": {"dx": %.17g, "frames": 1, "gravity": [0, 0, 0], "transfer": "%s", "flip_alpha": 1},
    "materials": {"bar": {"model": "fixed_corotated", "density": %g, "youngs_modulus": %g, "poisson_ratio": 0}},
    "objects": [{"shape": "box", "min": [%.17g, 0.48, 0.48], "max": [%.17g, %.17g, %.17g], "material": "bar",
                 "jitter": 0, "configuration": {"update": "%s"%s}}]})",
                dx, var.transfer.c_str(), kRho, kE, kXmin, kXmin + kL, 0.48 + kW, 0.48 + kW,
                var.update.c_str(),
                var.update == "adaptive" ? R"(, "epsilon": 0.002, "eta": 0.05)" : "");
  if (var.transfer != "flip") {  // flip_alpha is a flip-only key
    std::string t = text;
    t.erase(t.find(R"(, "flip_alpha": 1)"), 17);
    std::snprintf(text, sizeof text, "%s", t.c_str());
  }
  MpmSolver s = build_solver(parse_scene(text, "convergence.json"));
  const double k = M_PI / kL, w = k * std::sqrt(kE / kRho);
  auto& ps = s.particles();
  const auto& at = s.attributes();
  std::vector<double> X(ps.size());
  {
    const Vec3* x = ps.vec3(at.x);
    Vec3* v = ps.vec3(at.v);
    Mat3* C = at.C >= 0 ? ps.mat3(at.C) : nullptr;  // PIC/FLIP keeps none
    const std::int32_t* id = ps.int32(at.id);
    for (size_t p = 0; p < ps.size(); ++p) {
      const double xr = double(x[p][0]) - kXmin;
      X[size_t(id[p])] = xr;
      v[p] = Vec3(Real(kV + kA * w * std::cos(k * xr)), 0, 0);
      if (!C) continue;
      C[p] = Mat3::Zero();
      C[p](0, 0) = Real(-kA * w * k * std::sin(k * xr));
    }
  }
  const std::vector<double> X0 = X;
  int steps = int(std::lround(t_end / dt));
  for (int i = 0; i < steps; ++i) s.step(space, Real(dt));
  const double t = steps * dt;
  const Vec3* x = ps.vec3(at.x);
  const Vec3* v = ps.vec3(at.v);
  const std::int32_t* id = ps.int32(at.id);
  double eu = 0, ev = 0;
  for (size_t p = 0; p < ps.size(); ++p) {
    const double Xp = X0[size_t(id[p])];
    const double u = kV * t + kA * std::sin(w * t) * std::cos(k * Xp);
    // Symplectic Euler (kick, then drift with the new velocity) is leapfrog: v^{n+1} is the
    // velocity at t - dt/2, x^{n+1} the position at t (both second order in dt).
    const double ve = kV + kA * w * std::cos(w * (t - 0.5 * dt)) * std::cos(k * Xp);
    const double du = double(x[p][0]) - kXmin - Xp - u;
    const Vec3d dv(double(v[p][0]) - ve, v[p][1], v[p][2]);
    eu += du * du, ev += dv.squaredNorm();
  }
  Result r;
  r.dx = dx;
  r.disp = std::sqrt(eu / double(ps.size())) / kA;
  r.vel = std::sqrt(ev / double(ps.size())) / (kA * w);
  r.resets = s.aul()->maps().stats(0).updates;
  return r;
}

// Least-squares slope of log e vs log dx over the last n points (the finest spacings).
double order(const std::vector<Result>& r, int n, bool velocity) {
  n = std::min<int>(n, int(r.size()));
  double sx = 0, sy = 0, sxx = 0, sxy = 0;
  for (int i = int(r.size()) - n; i < int(r.size()); ++i) {
    const double a = std::log(r[size_t(i)].dx),
                 b = std::log(velocity ? r[size_t(i)].vel : r[size_t(i)].disp);
    sx += a, sy += b, sxx += a * a, sxy += a * b;
  }
  return (n * sxy - sx * sy) / (n * sxx - sx * sx);
}

Options parse(int argc, char** argv) {
  Options o;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> const char* {
      if (i + 1 >= argc) throw std::invalid_argument("missing value after " + a);
      return argv[++i];
    };
    if (a == "--levels")
      o.levels = std::atoi(next());
    else if (a == "--fit")
      o.fit = std::atoi(next());
    else if (a == "--csv")
      o.csv = next();
    else if (a == "--png")
      o.png = next();
    else if (a == "--check")
      o.check = std::atof(next());
    else if (a == "--backend")
      o.backend = next();
    else if (a == "--threads")
      o.threads = std::atoi(next());
    else
      throw std::invalid_argument("unknown option " + a);
  }
  if (o.levels < 2 || o.levels > 7 || o.fit < 2 || o.threads < 1)
    throw std::invalid_argument("--levels in [2, 7], --fit >= 2, --threads >= 1");
  return o;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    const Options o = parse(argc, argv);
    const exec::Space space(exec::parse_backend(o.backend), o.threads);
    std::vector<Variant> variants = {{"TL (s=0) MLS", "total_lagrangian", "mls"},
                                     {"A-UL MLS", "adaptive", "mls"},
                                     {"EULERIAN (s=n) MLS", "eulerian", "mls"},
                                     {"TL KERNEL-MPM (FLIP)", "total_lagrangian", "flip"}};
    if (o.check > 0) variants.resize(1);
    // dx = L/8 ... L/(8 2^(levels-1)); one dt for all: 0.4 of the finest grid's CFL step.
    std::vector<double> dxs;
    for (int l = 0; l < o.levels; ++l) dxs.push_back(kL / (8 << l));
    const double c = std::sqrt(kE / kRho), w = M_PI / kL * c;
    const double dt = 0.4 * dxs.back() / (c + kV + kA * w);
    const double t_end = 0.3 * 2 * M_PI / w;  // 0.3 of a period: the wave mid-swing
    std::printf(
        "bar L = %g m, c = %.3f m/s, period %.4f s, t_end %.4f s, dt %.3g s (%d steps), A = %g m, V = %g m/s\n",
        kL, c, 2 * M_PI / w, t_end, dt, int(std::lround(t_end / dt)), kA, kV);
    std::vector<std::vector<Result>> all;
    std::FILE* csv = o.csv.empty() ? nullptr : std::fopen(o.csv.c_str(), "w");
    if (!o.csv.empty() && !csv) throw std::runtime_error("cannot write " + o.csv);
    if (csv) std::fprintf(csv, "variant,dx,displacement_error,velocity_error,resets\n");
    for (const auto& var : variants) {
      std::vector<Result> rs;
      for (double dx : dxs) {
        const Result r = run(var, dx, dt, t_end, space);
        std::printf("%-22s dx %.5f  E_u %.4e  E_v %.4e  resets %llu\n", var.label.c_str(), dx,
                    r.disp, r.vel, (unsigned long long)r.resets);
        std::fflush(stdout);
        if (csv)
          std::fprintf(csv, "%s,%.6g,%.6e,%.6e,%llu\n", var.label.c_str(), dx, r.disp, r.vel,
                       (unsigned long long)r.resets);
        rs.push_back(r);
      }
      std::printf("%-22s order (finest %d): displacement %.2f, velocity %.2f\n", var.label.c_str(),
                  o.fit, order(rs, o.fit, false), order(rs, o.fit, true));
      all.push_back(rs);
    }
    if (csv) std::fclose(csv);
    if (!o.png.empty()) {
      LogLogPanel pu{"DISPLACEMENT ERROR E_U / A", "DX (M)", {}},
          pv{"VELOCITY ERROR E_V / (A W)", "DX (M)", {}};
      for (size_t i = 0; i < variants.size(); ++i) {
        PlotSeries su{variants[i].label, {}, {}}, sv{variants[i].label, {}, {}};
        for (const auto& r : all[i])
          su.x.push_back(r.dx), su.y.push_back(r.disp), sv.x.push_back(r.dx), sv.y.push_back(r.vel);
        pu.series.push_back(su), pv.series.push_back(sv);
      }
      PlotSeries ref{"SLOPE 2", {}, {}};  // through the TL finest point
      for (double dx : dxs)
        ref.x.push_back(dx),
            ref.y.push_back(all[0].back().disp * (dx / dxs.back()) * (dx / dxs.back()));
      pu.series.push_back(ref);
      write_png(o.png,
                plot_loglog("A-ULMPM CONVERGENCE: BAR STANDING WAVE + TRANSLATION", {pu, pv}));
    }
    if (o.check > 0) {
      const double pu = order(all[0], o.fit, false), pv = order(all[0], o.fit, true);
      const bool ok = pu >= o.check && pv >= o.check;
      std::printf("check: TL MLS orders displacement %.2f, velocity %.2f (need >= %.2f): %s\n", pu,
                  pv, o.check, ok ? "ok" : "FAILED");
      return ok ? 0 : 1;
    }
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "amalgam_aul_convergence: %s\n", e.what());
    return 2;
  }
}
