// Ordinary state-based peridynamics (Chen, Zhu, Zhao, Li, Wang: "Peridynamics-based fracture
// animation for elastoplastic solids", after Madenci & Oterkus 2014 and Mitchell 2011):
// elasticity (eqs. 2-9), deviatoric plasticity with a cap (eqs. 10-15), anisotropy through a
// matrix G in the influence weight (eq. 16), fracture by a critical stretch with damage (eqs.
// 17-18). Bonds in CSR form (offsets, neighbours, per-bond arrays). Every kernel gathers per particle
// over its own row (no scatter), so results are bitwise identical on every backend and thread
// count; the pair force uses both directed bonds i->j and j->i, the far end's per-bond values
// mirrored into row i (PdBonds::omega_r, shear_omega_r, plastic_r). Rows are processed in blocks
// whose arithmetic the compiler vectorises; sums run in lanes fixed per bond (PdBonds::lane), in
// bond order within a lane, broken bonds adding exact zeros, so compacting broken bonds away does
// not change a bit (see peridynamics.cpp).
//
// Notation: xi = x0_j - x0_i (reference bond), eta = y_j - y_i (current), L = |xi|, l = |eta|,
// e = l - L (extension), Lambda = (eta / l) . (xi / L), omega_ij = delta / |G_i xi| (eq. 16; G = I:
// eq. 4), V_j the neighbour's volume times the partial-volume factor nu_ij.
#pragma once

#include <algorithm>
#include <cstdint>
#include <functional>
#include <limits>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/math/types.hpp"

namespace amalgam {

// Which deviatoric extension the model uses.
//  Paper: e^d = e - (delta / 4) Lambda theta (eq. 8). Not zero bond by bond under a pure
//         dilation (short bonds negative, long ones positive; only its stress resultant
//         vanishes), so a yield test on it sees hydrostatic load.
//  Lps:   e^d = e - theta L / 3 (Silling et al. 2007, Mitchell 2011): exactly zero under a pure
//         dilation. Same bulk and shear moduli in the continuum limit.
enum class PdDeviatoric : std::uint8_t { Paper, Lps };
const char* pd_deviatoric_name(PdDeviatoric d);

// Which constitutive model.
//  Paper: the paper's ordinary state-based model (eqs. 2-9): theta_i = (3 / m) sum_j omega e Lambda
//         V_j with the continuum m = 4 pi delta^4 / 3 (omega = delta / L), the dilatational term of
//         A_ij along Lambda; with the surface correction by default (PdConstants).
//  Lps:   the linear peridynamic solid (Silling, Epton, Weckner, Xu, Askari 2007, eqs. 4.3-4.5 and
//         the form LAMMPS's pair peri/lps implements): m_i = sum_j omega L^2 V_j over the
//         particle's own family at t = 0 (so theta is exact under a dilation at surfaces too),
//         theta_i = (3 / m_i) sum_j omega L e V_j, t_ij = (3 kappa theta_i omega L + 15 mu omega
//         e^d) / m_i with e^d = e - theta L / 3. No fitted correction. The model the LAMMPS
//         comparisons of docs/validation.md run.
enum class PdModel : std::uint8_t { Paper, Lps };
const char* pd_model_name(PdModel m);

// Bond-breaking criterion.
//  Paper:     eq. 18, (e - e^p) / delta > s_c (1 + alpha phi): the extension over the horizon, so
//             at a given s_c a bond of length L breaks at the bond stretch s_c delta / L.
//  Classical: (e - e^p) / L > s_c (1 + alpha phi): the bond stretch (|xi + eta| - |xi|) / |xi|
//             (Silling and Askari 2005; LAMMPS peri, Peridigm). Between L = lc and delta = 3 lc the
//             two differ by the factor delta / L of each bond, so no single s_c maps one onto the
//             other (docs/validation.md).
enum class PdCriterion : std::uint8_t { Paper, Classical };
const char* pd_criterion_name(PdCriterion c);

struct PdMaterial {
  Real bulk = Real(1e6);   // kappa (Pa)
  Real shear = Real(6e5);  // mu (Pa)
  Real density = 1000;     // kg/m^3
  // Plasticity (eqs. 12-15): yield when A_dev^2 / 2 > psi0 (N^2/m^12); infinity = elastic. The
  // cap on |e^p| is plastic_cap * |xi| (the paper's gamma / |x_j - x_i|, Table 1).
  Real psi0 = std::numeric_limits<Real>::infinity();
  Real plastic_cap = std::numeric_limits<Real>::infinity();
  // Fracture (eq. 18): the bond breaks when (e - e^p) / delta > critical_stretch (1 + alpha phi),
  // phi the damage of the particle; infinity = unbreakable.
  Real critical_stretch = std::numeric_limits<Real>::infinity();
  Real alpha = 0;
  Mat3 G = Mat3::Identity();  // anisotropy (eq. 16)
};

// psi0 for a von Mises yield stress sigma_Y: under pure shear the largest per-bond deviatoric
// force density is A_dev = 4 omega b e^d = 4 delta b (tau / 2 mu) = 15 tau / (pi delta^4)
// (omega |xi| = delta), so yield at tau_Y = sigma_Y / sqrt(3) gives psi0 = A_c^2 / 2.
inline Real pd_psi0_from_yield_stress(Real sigma_y, Real delta) {
  const double ac = 15.0 * double(sigma_y) / (std::sqrt(3.0) * M_PI * std::pow(double(delta), 4));
  return Real(0.5 * ac * ac);
}

// Bonds of directed pairs i -> j (row i), rows sorted by j.
constexpr int kSumLanes = 8;

struct PdBonds {
  std::vector<std::uint64_t> offsets;   // n + 1
  std::vector<std::uint32_t> neighbor;  // j
  std::vector<std::uint64_t> reverse;   // index of the bond j -> i in row j
  std::vector<Real> length;             // L = |xi|
  std::vector<Real> omega;              // omega_ij (eq. 16, G of particle i) x the correction g_ij
  std::vector<Real> shear_omega;        // omega_ij (eq. 16) x the correction f_ij (PdConstants)
  std::vector<Real> volume;             // nu_ij V_j: the neighbour's (partial) volume
  std::vector<Real> plastic;            // e^p_ij (deviatoric plastic extension, eq. 10)
  std::vector<std::uint8_t> intact;     // 1 until the bond breaks (irreversible)
  // The reverse bond j -> i's omega, shear_omega and plastic extension, stored in this row's order
  // so that the force pass reads them sequentially instead of gathering from row j (those
  // gathers were ~40 % of the force pass). omega_r and shear_omega_r are constants
  // (pd_mirror_bonds); plastic_r is kept in step by pd_dilatation, which writes the slot
  // reverse[k] whenever plastic[k] changes (each slot has one writer: deterministic).
  std::vector<Real> omega_r, shear_omega_r, plastic_r;
  // Sum lanes. The passes sum a row's terms in kSumLanes independent chains (a single chain in
  // bond order was a 3-cycle add latency per bond: ~15 % of a step), then combine the lanes in a
  // fixed order. A bond's lane is its position in its row *as built*, mod kSumLanes, and stays
  // with it through compaction (lane), so a compacted row sums its bonds in the same lanes in the
  // same order; the removed bonds were broken, whose terms are exact zeros, so the sums are
  // bitwise those of the uncompacted row. dense[i] = 1 while row i still holds every bond it was
  // built with (lane = position mod kSumLanes: the vectorised path).
  std::vector<std::uint8_t> lane;   // per bond
  std::vector<std::uint8_t> dense;  // per row
  std::size_t size() const { return neighbor.size(); }
  std::size_t particles() const { return offsets.empty() ? 0 : offsets.size() - 1; }
};

struct PdParams {
  Real horizon = Real(0.03);  // delta
  Real spacing = Real(0.01);  // lattice spacing lc (partial volumes, contact distance)
  PdModel model = PdModel::Paper;
  PdDeviatoric deviatoric = PdDeviatoric::Paper;  // PdModel::Lps: always Lps
  PdCriterion criterion = PdCriterion::Paper;
  const PdMaterial* materials = nullptr;
  // Energy-consistent forces (with the surface correction): A_ij gains the derivative of the
  // deviatoric energy through theta (see pd_dilatation), so that the forces are the gradient of
  // sum_i W_i V_i. The paper's force leaves it out; it vanishes where the family's moments are
  // isotropic (the bulk of a corrected lattice), but at edges and corners, where the correction
  // can only fit part of the moments, leaving it out gave a non-symmetric stiffness whose modes
  // grew exponentially whatever the time step (flutter).
  bool consistent = false;
  // Some material yields (a finite psi0). When none does, every plastic extension stays 0 and the
  // passes skip reading them (8 of the force pass's 37 bytes per bond): bitwise the same results.
  bool plastic = true;
};

// Per-particle constants of the model (set up once from the reference configuration).
//   m_i: theta normaliser, theta_i = (3 / m_i) sum_j omega s Lambda L V_j (eq. 5 with m = 4 pi
//        delta^4 / 3 gives the paper's 9 / (4 pi delta^4));
//   a_i = 3 kappa / (2 m_i) (eq. 9: 9 kappa / (8 pi delta^4));
//   b_i = 15 mu / (2 pi delta^5) (eq. 9); bond ij's deviatoric stiffness is 4 b_i shear_omega_ij;
//   kappa_i: the delta / 4 of e^d = e - kappa Lambda theta (eq. 8).
// Without the correction omega is eq. 16's, shear_omega = omega, m and kappa the continuum values.
// PdModel::Lps: omega is eq. 16's, shear_omega = omega, m_i = sum_j omega L^2 V_j (its own family),
// a_i = 3 kappa / (2 m_i), b_i = 15 mu / (2 m_i) (A_ij = 2 t_ij of Silling et al. 2007), kappa_i
// unused (e^d = e - theta L / 3).
//
// The surface/lattice correction (option, on by default) makes every particle's own stress
// 1/2 sum_j A_ij (eta/l) (x) xi V_j exact for every homogeneous deformation, at interior and
// near-surface particles alike, in the spirit of the position-aware linear solid (Mitchell,
// Silling, Littlewood 2015). Per bond it scales the dilatational weight, omega = omega_16 g_ij,
// and the deviatoric one, shear_omega = omega_16 f_ij, with factors as close to 1 as possible
// (least squares, weight omega0 V) under moment constraints against the continuum (omega0 =
// delta / L, eq. 4):
//   g: sum_j omega0 g L n_a n_b V_j = (m / 3) delta_ab (6 constraints): theta exact for every
//      homogeneous strain, and the dilatational stress isotropic;
//   f: sum_j omega0 f L^2 n_a n_b n_c n_d V_j = (pi delta^5 / 15) (d_ab d_cd + d_ac d_bd +
//      d_ad d_bc) (15) and sum_j omega0 f L n_a n_b V_j = (m / 3) delta_ab (6): the deviatoric
//      stiffness isotropic with the continuum shear modulus, and the paper's e^d (kappa = delta /
//      4) free of stress under a dilation.
// m and kappa keep their continuum values. Why: the lattice's fourth moments are cubic, not
// isotropic (uncorrected, (C11 - C12) / 2 = 0.81-0.96 C44 on the delta = 3.015 lc lattice, so E
// is 12 % off and nu 0.32 for an input 0.25), and near a free surface both moments lose the
// missing part of the family anisotropically (a scalar per particle over-stiffens the directions
// along the surface: a 6 x 6 bar was 8 % fast). The factors are positive by construction
// (exponential family: the fit minimises relative entropy, see fit_factors). Families that cannot
// meet the constraints (an edge, cut by two faces, or a sheet one layer thick) fall back step by
// step: g = 1 with m_i = sum_j omega L V_j (LPS's discrete normaliser, theta exact under
// dilation); f fitted to the fourth moments only, kappa_i = sum_j omega f L^2 V_j / (3 sum_j
// omega f L V_j); else one factor normalising the mean coordinate shear sum.
struct PdConstants {
  std::vector<Real> m, a, b, kappa;
  std::vector<std::uint8_t>
      fitted;  // correction: 2 full fit, 1 axis-diagonal fit (edges), 0 scalar fallback (or off)
  std::vector<std::int32_t> bonds0;  // bonds at t = 0 (for the damage phi = 1 - n / N)
};

// A particle view for the kernels.
struct PdView {
  std::size_t n = 0;
  const Vec3* x0 = nullptr;  // reference positions
  const Vec3* x = nullptr;   // current positions
  const Vec3* x_lo =
      nullptr;  // their low parts (null: 0); eta = xi + (u_j - u_i), u = x - x0 + x_lo
  const Real* volume = nullptr;
  const std::int32_t* material = nullptr;
  Real* theta = nullptr;
  Real* q =
      nullptr;  // b_i (3 / m_i) Q_i: the consistent term (PdParams::consistent), written by pd_dilatation
  Real* damage = nullptr;
  const Real* m = nullptr;
  const Real* a = nullptr;
  const Real* b = nullptr;
  const Real* kappa = nullptr;
  const std::int32_t* bonds0 = nullptr;
};

// Bonds within the horizon (L <= delta, a particle is not its own neighbour) by a cell-binned
// search over cells of size delta; rows sorted by neighbour index, so the list does not depend
// on the thread count. partial_volume: nu_ij = (delta + lc/2 - L) / lc for L > delta - lc/2
// (the share of the neighbour's cell inside the horizon, as LAMMPS does), else 1.
void pd_build_bonds(const exec::Space& space, const Vec3* x0, const Real* volume,
                    const std::int32_t* material, std::size_t n, const PdParams& prm,
                    bool partial_volume, PdBonds& bonds);

// Some rows of the bond list (a distributed set-up builds only the rows a rank needs): row q is
// particle rows[q] of x0 / volume / material; neighbours stay indices into x0 (the whole set),
// reverse is kNoReverse. Lanes and dense as pd_build_bonds gives the same rows.
void pd_build_bond_rows(const exec::Space& space, const Vec3* x0, const Real* volume,
                        const std::int32_t* material, std::size_t n, const std::uint32_t* rows,
                        std::size_t m, const PdParams& prm, bool partial_volume, PdBonds& bonds);
// The row lengths of the particles rows[0..m) (nothing stored).
std::vector<std::uint64_t> pd_count_bonds(const exec::Space& space, const Vec3* x0, std::size_t n,
                                          const std::uint32_t* rows, std::size_t m, Real horizon);

// A bond list that holds some rows of the whole set (pd_build_bond_rows): row q's particle, and
// the largest bond volume over every row of the whole set (a family's signature is relative to
// it; < 0: these rows' largest).
struct PdRowSubset {
  const std::uint32_t* particle = nullptr;
  double vmax = -1;
  // Optional: the rows' family keys (pd_family_keys of these rows), so they are not hashed again.
  const std::uint64_t* key = nullptr;
  // Optional: rows whose family another rank fits (given[q] = 1: not fitted here). `exchange`
  // is called after this call's own fits and before any row copies its family's values; it sets
  // the given rows' constants (out's per-row values, omega and shear_omega of their bonds).
  const std::uint8_t* given = nullptr;
  std::function<void(PdConstants& out, PdBonds& bonds)> exchange;
};

// m, a, b, kappa, bonds0 per particle and the bonds' shear_omega (see PdConstants). With a subset
// the constants are those of its rows, each family fitted once at its first row (the whole set's
// first member of each family must come first for the whole set's bits), and the mirrored arrays
// (omega_r, ...) are left to the caller (the reverse bonds may be in other rows). Returns the
// number of families fitted here (given rows not counted).
std::size_t pd_constants(const exec::Space& space, const Vec3* x0, const std::int32_t* material,
                         PdBonds& bonds, const PdParams& prm, bool surface_correction,
                         PdConstants& out, const PdRowSubset* subset = nullptr);
// The families' hash keys pd_constants groups rows by (equal families, equal keys).
std::vector<std::uint64_t> pd_family_keys(const exec::Space& space, const Vec3* x0,
                                          const std::int32_t* material, const PdBonds& bonds,
                                          const PdParams& prm, const PdRowSubset* subset = nullptr);

// Fills omega_r, shear_omega_r and plastic_r from the reverse bonds (after the constants, a
// compaction or a restore).
void pd_mirror_bonds(const exec::Space& space, PdBonds& bonds);

// theta_i over the intact bonds (eq. 5), then the plastic return of each bond of row i (eqs.
// 11-15): trial A_dev = 4 omega b (e^d - e^p); beyond the yield surface e^p grows by
// (A_dev - A_c) / (4 omega b), which puts A_dev exactly on the surface A_c = sqrt(2 psi0)
// sign(A_dev), then |e^p| is capped at plastic_cap L. (Eq. 14 as printed divides by 2b, which
// equals this only where 2 omega = 1; we use the exact projection.)
// With PdParams::consistent it also writes q_i = b_i (3 / m_i) Q_i, Q_i = sum_j shear_omega
// (e^d - e^p) d_j V_j, d_j = -de^d/dtheta (kappa Lambda, paper; L / 3, LPS): the deviatoric
// energy b sum shear_omega (e^d - e^p)^2 V depends on every bond through theta, and its
// derivative adds -4 omega Lambda q_i to every A_ij of the row.
// scratch (optional): per-particle records of the passes, kept by the caller so that a step does
// not allocate and zero them (n x 32 and n x 48 bytes) on every call.
struct PdScratch {
  std::vector<Real> records;
};
void pd_dilatation(const exec::Space& space, const PdView& p, PdBonds& bonds, const PdParams& prm,
                   PdScratch* scratch = nullptr);

// Pair force per bond (eqs. 1-3, 7, 11): A_ij = 4 omega_ij (a_i Lambda theta_i + b_i (e^d_ij -
// e^p_ij)), and the force density on i is sum_j (A_ij + A_ji) / 2 (eta / l) V_j (the paper's
// T_i<x_j - x_i> - T_j<x_i - x_j>). stress (optional): sigma_i = 1/2 sum_j f_ij (x) xi V_j (the
// peridynamic stress of a homogeneous deformation). fracture: after the force, bonds whose
// criterion (eq. 18) holds from either end break; both rows decide alike, so breaking stays
// symmetric. Returns nothing; force is a density (N/m^3). intact (optional): the pass also does
// pd_damage's work, each row's damage right after its fracture (the row's flags are then in
// cache: one pass over the bonds fewer per step), and stores the number of intact directed bonds.
void pd_forces(const exec::Space& space, const PdView& p, PdBonds& bonds, const PdParams& prm,
               bool fracture, Vec3* force, Mat3* stress, PdScratch* scratch = nullptr,
               std::uint64_t* intact = nullptr);

// Short-range contact (fragments, or bodies, meeting), as LAMMPS's peri styles do: particles
// closer than `distance` that share no intact bond repel with force density
// c_S (distance - r) / delta V_j, c_S = 15 * 18 kappa / (pi delta^4) (kappa averaged over the
// pair); for a pair whose bond broke the distance is min(distance, 0.9 L_ij) (LAMMPS), so
// particles that started closer (tetrahedron barycentres) are not pushed apart when it breaks.
// Candidates come from a Verlet list: every pair within distance + skin at the last
// build (CSR, rows sorted), rebuilt by the caller once some particle moved more than skin / 2.
// A pair whose bond broke touches below min(distance, 0.9 L) (LAMMPS's rule). Such a bond must
// stay stored while 0.9 L < distance (pd_compact_bonds), since the contact reads its length.
inline Real pd_broken_pair_distance(Real L, Real distance) {
  return std::min(distance, Real(0.9) * L);
}
inline bool pd_contact_reads_broken_bond(Real L, Real distance) {
  return Real(0.9) * L < distance;
}
struct PdContactList {
  std::vector<std::uint64_t> offsets;
  std::vector<std::uint32_t> neighbor;
  std::vector<Vec3> x_built;  // positions at the build
};
void pd_build_contact_list(const exec::Space& space, const Vec3* x, std::size_t n, Real radius,
                           PdContactList& list);
// Largest displacement since the list was built.
Real pd_max_displacement(const exec::Space& space, const Vec3* x, const PdContactList& list);
// Adds the contact force densities.
void pd_contact_forces(const exec::Space& space, const PdView& p, const PdBonds& bonds,
                       const PdParams& prm, Real distance, const PdContactList& list, Vec3* force);

// phi_i = 1 - n_i / N_i (eq. 18's damage); returns the number of intact directed bonds.
std::uint64_t pd_damage(const exec::Space& space, const PdView& p, const PdBonds& bonds);

// Removes broken bonds from the CSR arrays (rows keep their order, every per-bond array is
// copied, reverse indices rebuilt) and returns how many. Broken bonds with 0.9 L below
// contact_distance stay (0: none): pd_contact_forces lets such a pair touch only below 0.9 L,
// so removing its bond would change the physics. Broken bonds add exact zeros to every sum and
// keep their lanes (PdBonds::lane), so a compacted list gives the same sums in the same order: the
// run continues bitwise as without compaction. Pays once many bonds are broken (measured in
// docs/benchmarks.md).
std::uint64_t pd_compact_bonds(const exec::Space& space, PdBonds& bonds, Real contact_distance = 0);

// Keeps the rows i with keep_row[i] != 0 whole and empties the others (a rank of a distributed
// run keeps the rows of the particles it owns): every per-bond array is copied, the mirrored
// arrays (omega_r, shear_omega_r, plastic_r) included, so a kept row's sums are bitwise those of
// the full list. reverse[k] points into the new layout where row j is kept, else kNoReverse.
constexpr std::uint64_t kNoReverse = ~std::uint64_t(0);
void pd_keep_rows(const exec::Space& space, PdBonds& bonds,
                  const std::vector<std::uint8_t>& keep_row);

// Restricts `bonds` (the full list built from the reference configuration) to the rows given by
// offsets/neighbor (a compacted layout read from a checkpoint): each given row must be a sorted
// subsequence of the full row; returns false (bonds unchanged) if not.
bool pd_restrict_bonds(const exec::Space& space, PdBonds& bonds,
                       const std::vector<std::uint64_t>& offsets,
                       const std::vector<std::uint32_t>& neighbor);

// The bond passes (pd_dilatation, pd_forces, pd_damage) are compiled once per instruction set
// (kernels/peridynamics_passes.cpp; core/exec/simd.hpp), each copy in its namespace with one of
// these tables; the functions above call the table of exec::simd_path()
// (kernels/peridynamics_dispatch.cpp).
struct PdKernelTable {
  void (*dilatation)(const exec::Space&, const PdView&, PdBonds&, const PdParams&, PdScratch*);
  void (*forces)(const exec::Space&, const PdView&, PdBonds&, const PdParams&, bool, Vec3*, Mat3*,
                 PdScratch*, std::uint64_t*);
  std::uint64_t (*damage)(const exec::Space&, const PdView&, const PdBonds&);
};

}  // namespace amalgam
