#include "solvers/estimate.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <sstream>

#include "core/errors.hpp"
#include "core/geometry/triangle_mesh.hpp"
#include "kernels/mpm_transfers.hpp"
#include "solvers/mpm_solver.hpp"
#include "solvers/pd_solver.hpp"

namespace amalgam {

namespace {

std::string object_path(std::size_t k) {
  return "/objects/" + std::to_string(k);
}

// Particles of an object: sample_object's lattice (solvers/scene_spec.cpp) counted, the curved
// shapes by their volume over the lattice cell.
double object_particles(const ObjectSpec& o, double dx) {
  if (o.shape == ObjectShape::TetMesh) return o.tets ? double(o.tets->tets.size()) : 0.0;
  const double h = dx / std::cbrt(double(o.particles_per_cell));
  double box = 1;
  for (int a = 0; a < 3; ++a) {
    const double cells = (double(o.max[a]) - double(o.min[a])) / h;
    box *= std::max(1.0, o.shape == ObjectShape::Box ? std::round(cells) : std::ceil(cells));
  }
  const double r = double(o.radius);
  double volume = 0;
  switch (o.shape) {
    case ObjectShape::Box:
      return box;
    case ObjectShape::Sphere:
      volume = 4.0 / 3.0 * M_PI * r * r * r;
      break;
    case ObjectShape::Cylinder:
      volume = M_PI * r * r * double(o.height);
      break;
    case ObjectShape::Torus:
      volume = 2.0 * M_PI * M_PI * r * double(o.minor_radius) * double(o.minor_radius);
      break;
    case ObjectShape::Mesh:
      volume = o.mesh ? std::abs(enclosed_volume(*o.mesh)) : 0.0;
      break;
    case ObjectShape::TetMesh:
      break;
  }
  return std::min(box, std::ceil(volume / (h * h * h)));
}

// The largest speed an object starts with: its velocity plus its spin at the farthest corner of
// its bounding box.
Vec3 fastest_initial_velocity(const ObjectSpec& o) {
  Vec3 far = Vec3::Zero();
  for (int c = 0; c < 8; ++c) {
    const Vec3 corner((c & 1) ? o.max[0] : o.min[0], (c & 2) ? o.max[1] : o.min[1],
                      (c & 4) ? o.max[2] : o.min[2]);
    const Vec3 v = o.velocity + o.angular_velocity.cross(corner - o.center);
    if (v.norm() > far.norm()) far = v;
  }
  return far;
}

// P2G's blocks kept between substeps (MpmSolver::p2g_blocks_), one per bin, of the path these
// settings take: the plain two passes' (8 + order)^3-node blocks, the fused pass's dilated
// (10 + order)^3-node 8-lane blocks, the lazily sorted two passes' dilated blocks with the plain
// lanes. A path whose blocks would exceed its budget runs without them (the colour phases) or
// falls back to the plain ones. The budgets are MpmSolver's (p2g_blocks_budget,
// dilated_blocks_budget; `EstimateBlocks.MatchWhatTheSolverAllocates` compares the two). Several ranks
// keep their own blocks (sorting every substep: the bins that reach ghosts, and interior ones up
// to a cap; re-sorting only when needed: every bin's dilated block plus one per other rank's bin
// whose parts arrive, solvers/mpm_lazy_distributed.cpp): counted as one process's.
double p2g_block_bytes(const MpmSettings& s, bool distributed, bool fused_positions, double bins,
                       double particles) {
  const double plain_budget = double(MpmSolver::p2g_blocks_budget(std::size_t(particles)));
  const double dilated_budget = double(MpmSolver::dilated_blocks_budget(std::size_t(particles)));
  const bool fused = fuses(s, distributed);
  const double real = double(sizeof(Real));
  const int ch = p2g_channels(s.transfer, fused || fused_positions);
  double plain = bins * double(p2g_block_reals(s.order, ch)) * real;
  if (plain > plain_budget) plain = 0;
  double dilated = 0;
  if (fused)
    dilated = bins * double(g2p2g_block_reals(s.order)) * real;
  else if (sorts_when_needed(s))
    dilated = bins * double(dilated_block_reals(s.order, ch)) * real;
  if (dilated > dilated_budget) dilated = 0;
  return std::max(plain, dilated);  // the blocks only grow
}

// MPM: one particle per object, at its fastest initial velocity, in a solver of the scene's
// settings and materials: its attribute layout gives the bytes per particle, its stable_dt the
// first substep (wave speeds, speeds, viscosity and max_dt exactly as the run computes them).
void estimate_mpm(const SceneSpec& s, bool rest_positions, int ranks, RunEstimate& e) {
  MpmSettings settings = s.mpm;
  // Domain corners add no particle attributes of their own; particle domains transfer by
  // PIC/FLIP (whatever simulation.transfer says): no C unless a material is viscous, and the
  // second grid set.
  if (settings.domains.enabled) settings.transfer = Transfer::PicFlip;
  settings.domains.enabled = false;
  // Several ranks run the two passes (fuses): no split grid set.
  if (ranks > 1) settings.fused = false;
  MpmSolver probe(settings, s.materials, {}, s.heat_sources);
  if (rest_positions) probe.keep_rest_positions();
  const double dx = double(s.mpm.dx);
  // The fused pass and the lazily sorted two passes scatter into dilated blocks.
  const bool dilated = fuses(settings, ranks > 1) || sorts_when_needed(settings);
  for (std::size_t k = 0; k < s.objects.size(); ++k) {
    const ObjectSpec& o = s.objects[k];
    const Vec3 centre = (o.min + o.max) / 2;
    const Real h = Real(dx / std::cbrt(double(o.particles_per_cell)));
    probe.add_particles({centre}, fastest_initial_velocity(o), Vec3::Zero(), centre, o.material,
                        h * h * h, o.temperature, o.configuration);
    // Leaves (8 dx) over the bounding box widened by the stencil, and with the dilated blocks
    // one more on the - side (update_grid_fused: the leaves the blocks' margin reaches).
    double leaves = 1;
    for (int a = 0; a < 3; ++a)
      leaves *= std::ceil((double(o.max[a]) - double(o.min[a]) + 4 * dx) / (kLeafDim * dx)) +
                (dilated ? 2 : 1);
    e.grid_leaves += leaves;
    // Bins: the leaves the bounding box itself overlaps.
    double bins = 1;
    for (int a = 0; a < 3; ++a)
      bins *= std::ceil((double(o.max[a]) - double(o.min[a])) / (kLeafDim * dx)) + 1;
    e.bins += bins;
  }
  for (const EmitterSpec& em : s.emitters) {  // emitted particles start at the emitter's velocity
    const Vec3 centre = (em.min + em.max) / 2;
    const Real h = Real(em.spacing(s.mpm.dx));
    probe.add_particles({centre}, em.velocity, Vec3::Zero(), centre, em.material, h * h * h,
                        em.temperature);
  }
  try {
    e.dt = double(probe.stable_dt(exec::Space()));
  } catch (const SimulationError& err) {
    throw InputError("/objects: the initial velocities trip the stability guard at once (" +
                     std::string(err.what()) + ")");
  }
  const double particle_bytes = double(probe.particles().bytes_per_particle() +
                                       probe.particles().state_bytes_per_particle()) +  // snapshot
                                double(MpmSolver::binning_bytes_per_particle());
  // A-ULMPM with colliders or contact between objects rasterises the node positions in P2G's
  // blocks (8 lanes; MpmSolver::fused_positions).
  const bool positions = settings.configuration_maps &&
                         (!s.colliders.empty() ||
                          (s.mpm.contact.mode != ObjectContactMode::None && s.objects.size() > 1));
  e.block_bytes = p2g_block_bytes(settings, ranks > 1, positions, e.bins, e.particles);
  e.bytes += e.particles * particle_bytes + e.grid_leaves * double(probe.grid().bytes_per_leaf()) +
             e.block_bytes;
}

// Peridynamics: a lattice block per material (interior particles with full horizons) in a solver
// of the scene's settings: its critical step and bonds per particle, and its layout's bytes.
void estimate_pd(const SceneSpec& s, RunEstimate& e) {
  const double lc = double(s.pd.spacing), delta = double(s.pd.horizon);
  const int n = int(std::ceil(2 * delta / lc)) + 3;  // horizon_factor <= 8: at most 19
  PdSolver probe(s.pd, s.pd_materials, {});
  const Real v = Real(lc * lc * lc);
  for (std::size_t m = 0; m < s.pd_materials.size(); ++m) {
    std::vector<Vec3> x;
    const double x0 = double(m) * (n + 4 * delta / lc + 4) * lc;
    for (int i = 0; i < n; ++i)
      for (int j = 0; j < n; ++j)
        for (int k = 0; k < n; ++k) x.push_back(Vec3d(x0 + i * lc, j * lc, k * lc).cast<Real>());
    probe.add_particles(x, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), int(m), v);
  }
  probe.initialize(exec::Space());
  e.dt = double(probe.stable_dt(exec::Space()));
  const PdBonds& b = probe.bonds();
  std::uint64_t widest = 0;
  for (std::size_t i = 0; i + 1 < b.offsets.size(); ++i)
    widest = std::max(widest, b.offsets[i + 1] - b.offsets[i]);
  e.bonds = e.particles * double(widest);
  // Per bond: neighbour, reverse index, 8 Reals, intact and lane flags; the frame-start snapshot
  // keeps plastic, plastic_r and intact.
  const double bond_bytes = 4 + 8 + 8 * sizeof(Real) + 2 + (2 * sizeof(Real) + 1);
  e.bytes += e.particles * (double(probe.particles().bytes_per_particle() +
                                   probe.particles().state_bytes_per_particle()) +
                            8) +
             e.bonds * bond_bytes;
  e.bond_bytes = e.bonds * bond_bytes;
  for (std::size_t k = 0; k < s.objects.size(); ++k) {
    const double speed = double(fastest_initial_velocity(s.objects[k]).norm());
    if (!(speed <= double(s.pd.max_speed)))
      throw InputError(
          object_path(k) + ": starts at up to " + std::to_string(speed) +
          " m/s, above simulation.max_speed = " + std::to_string(double(s.pd.max_speed)) + " m/s");
  }
}

std::string human(double x) {
  char b[32];
  std::snprintf(b, sizeof b, x < 1e5 ? "%.0f" : "%.3g", x);
  return b;
}

std::string bytes_text(double b) {
  char s[32];
  if (b >= 1e9)
    std::snprintf(s, sizeof s, "%.1f GB", b / 1e9);
  else
    std::snprintf(s, sizeof s, "%.0f MB", std::max(1.0, b / 1e6));
  return s;
}

}  // namespace

RunEstimate estimate_run(const SceneSpec& s, bool rest_positions, int ranks) {
  RunEstimate e;
  const double dx = double(s.mpm.dx);
  for (std::size_t k = 0; k < s.objects.size(); ++k) {
    const ObjectSpec& o = s.objects[k];
    const double h = dx / std::cbrt(double(o.particles_per_cell));
    try {
      check_grid_range(o.min.cast<double>(), o.max.cast<double>(), s.method == Method::Mpm ? dx : h,
                       "the object");
    } catch (const InputError& err) {
      throw InputError(object_path(k) + ": " + err.what());
    }
    e.particles += object_particles(o, dx);
  }
  // Emitters: the most particles each can emit (memory is sized for all of them alive at once).
  for (const EmitterSpec& em : s.emitters) {
    try {
      check_grid_range(em.min.cast<double>(), em.max.cast<double>(), dx, "the emitter");
    } catch (const InputError& err) {
      throw InputError(em.where + ": " + err.what());
    }
    e.particles += em.max_particles(s.mpm.dx);
  }
  for (std::size_t k = 0; k < s.colliders.size(); ++k) {
    const ColliderSpec& c = s.colliders[k];
    if (!c.mesh) continue;
    Vec3d lo, hi;
    mesh_bounds(*c.mesh, lo, hi);
    try {
      check_grid_range(lo, hi, dx, "the mesh");
    } catch (const InputError& err) {
      throw InputError("/colliders/" + std::to_string(k) + ": " + err.what());
    }
  }
  if (s.method == Method::Mpm)
    estimate_mpm(s, rest_positions, ranks, e);
  else
    estimate_pd(s, e);
  // The step in the build's precision: a Real that is not a normal number cannot advance time.
  if (!(e.dt >= double(std::numeric_limits<Real>::min())) || !std::isfinite(e.dt)) {
    std::ostringstream os;
    os << "/simulation: the stable substep would be " << e.dt << " s, not a normal " << real_name()
       << " (check dx, cfl, max_dt and the materials' stiffness)";
    throw InputError(os.str());
  }
  e.substeps_per_frame = std::ceil((1.0 / s.fps) / e.dt);
  e.substeps = e.substeps_per_frame * double(s.frames);
  return e;
}

std::string describe(const RunEstimate& e) {
  std::ostringstream os;
  os << human(e.particles) << " particles, ";
  if (e.bonds > 0)
    os << human(e.bonds) << " bonds, ";
  else
    os << human(e.grid_leaves) << " grid leaves, ";
  char dt[32];
  std::snprintf(dt, sizeof dt, "%.3g", e.dt);
  os << "about " << bytes_text(e.bytes) << ", " << human(e.substeps_per_frame)
     << " substeps per frame (first dt " << dt << " s), " << human(e.substeps) << " substeps";
  return os.str();
}

std::string over_limits(const RunEstimate& e, double available_bytes) {
  std::string out;
  if (available_bytes > 0 && e.bytes > available_bytes)
    out += "needs about " + bytes_text(e.bytes) + " of memory, more than the " +
           bytes_text(available_bytes) + " available. ";
  if (e.substeps_per_frame > kMaxSubstepsPerFrame)
    out += "a frame would take " + human(e.substeps_per_frame) + " substeps, more than " +
           human(kMaxSubstepsPerFrame) + ". ";
  if (e.substeps > kMaxSubsteps)
    out += "the run would take " + human(e.substeps) + " substeps, more than " +
           human(kMaxSubsteps) + ". ";
  if (!out.empty()) out.pop_back();
  return out;
}

}  // namespace amalgam
