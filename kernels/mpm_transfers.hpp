// Explicit MPM transfer kernels over the block-sparse grid: P2G, grid update, G2P.
//
// Transfers (selectable per solver):
//   PicFlip : v_p <- alpha (v_p + sum w dv_i) + (1 - alpha) sum w v_i   (alpha = 0 is PIC)
//   Apic    : p_i += w m_p (v_p + C_p (x_i - x_p)), C_p = D_p^{-1} sum w v_i (x_i - x_p)^T
//             (Jiang et al. 2015; A-ULMPM eq. 28)
//   Mls     : p_i += w (m_p v_p + (m_p C_p - dt V_p^0 D_p^{-1} P_p F_p^T)(x_i - x_p))
//             (Hu et al. 2018, MLS-MPM; A-ULMPM Sec. 5.8: grad v_p = C_p)
// Forces (PicFlip, Apic): f_i = -sum_p V_p^0 P_p F_p^T grad w_ip (course report).
// The stress P_p F_p^T = tau_p is the material's Kirchhoff stress (core/materials/material.hpp),
// which may depend on grad v_p = C_p (viscosity): G2P stores grad v_p in C_p for every transfer
// whose particles keep C (PIC/FLIP of inviscid materials keep none: MpmSolver::keeps_affine).
// F update: F_p <- (I + dt grad v_p) F_p.  (The course report's code multiplies on the right,
// F (I + dt grad v); the left product is the correct push-forward and what we implement.)
//
// P2G is race-free and deterministic: for each of the 8 colours, a parallel_for over that
// colour's bins scatters each bin's particles, in sorted order, into a private block of
// (8 + Order)^3 nodes, then adds the block into the bin's 8 leaves with plain adds. With room
// for every bin's block (MpmGridView::blocks), all bins scatter in one loop and each leaf then
// adds its (at most 8) blocks in colour order: every node sums the same values in the same order.
#pragma once

#include <array>
#include <cstdint>
#include <functional>

#include "core/exec/exec.hpp"
#include "core/materials/material.hpp"
#include "core/math/left_cauchy_green.hpp"
#include "core/math/types.hpp"
#include "core/geometry/colliders.hpp"
#include "kernels/stability_check.hpp"
#include "sparse_grid/binning.hpp"

namespace amalgam {

enum class Transfer { PicFlip, Apic, Mls };
struct MaterialUpdateParams;  // kernels/material_update.hpp
const char* transfer_name(Transfer t);

// What the transfer kernels read and write of the particles (SoA pointers).
struct MpmParticleView {
  Vec3* x;  // positions x + x_lo (below); kernels read x
  Vec3* v;
  Mat3* C;  // null for PIC/FLIP of inviscid materials (nothing reads it; kernels pass zeros)
  Mat3* F;  // null where the particles keep J alone (below)
  const Real* volume0;  // mass: MaterialParams::mass(volume0) of the particle's material
  const std::int32_t* material;
  std::size_t n;
  // The low parts of x and F (core/math/types.hpp: add_compensated); null: plain Real state
  // (kernel tests). A-ULMPM's F is F_s F_0s and has no low part.
  Vec3* x_lo = nullptr;
  Mat3* F_lo = nullptr;
  // J = det F instead of F (MpmSolver::keeps_J_only: every material a fluid, explicit, Eulerian):
  // G2P takes J <- det(I + dt grad v) J, the stress reads J, and nothing resets F.
  Real* J = nullptr;
  // b - I of the left Cauchy-Green tensor b = F F^T instead of F (MpmSolver::keeps_b: explicit,
  // Eulerian, no output of F; core/math/left_cauchy_green.hpp): G2P advances it, the stress and
  // the material update read its Cholesky factor as F (every material is isotropic).
  SymDev* b = nullptr;
  Real* plastic = nullptr;      // per-particle plastic scalar, if any material has one
  Real* temperature = nullptr;  // per-particle temperature (K), if any material melts
  // Adaptively updated Lagrangian mode (A-ULMPM Sec. 5), on when X_ref is set: weights and
  // gradients are measured at the reference positions X^s (stencil positions), C_p holds
  // grad_s v_p, F_s = F^{sn} and F_0s = F^{0s} with F = F^{0n} = F_s F_0s (eq. 32). P2G uses
  // the stress P^0 (F^{0s})^T = tau F_s^{-T} (eq. 20); G2P updates F_s += dt grad_s v (eq. 30).
  const Vec3* X_ref = nullptr;
  Mat3* F_s = nullptr;
  const Mat3* F_0s = nullptr;
};

// check_range (kernels/stability_check.hpp) of particles [i0, i1) of p, on F or J.
template <class Index>
inline void check_particles(StabilityCheck& acc, Index i0, Index i1, const MpmParticleView& p,
                            const StabilityLimits& lim) {
  if (p.J)
    check_range(acc, i0, i1, p.v, p.J, lim);
  else if (p.b)
    check_range(acc, i0, i1, p.v, p.b, lim);
  else
    check_range(acc, i0, i1, p.v, p.F, lim);
}

// Distributed P2G (solvers/mpm_distributed.cpp): the part of another rank's bin block that falls
// in leaf `leaf` of this rank, the block's neighbour t (0..7: +x, +y, +z by bit, as nbr8), its
// nodes i < ni, j < nj, k < nk of the leaf (8, or Order on a + side) z fastest, CH Reals each.
struct P2GImport {
  std::int32_t leaf;
  std::int32_t t;
  const Real* data;
};
// Nodes of a bin block's part in its neighbour leaf t, and that part copied out of the block
// (`block`: the (8 + order)^3 x ch block of p2g_blocks) in P2GImport's layout.
int block_part_nodes(int order, int t);
// Reals of a bin's P2G block ((8 + order)^3 nodes of ch lanes): p2g_blocks' `keep` stride.
std::size_t p2g_block_reals(int order, int ch);
// Lanes of a P2G block: 8 for PIC/FLIP (force) or with fused node positions (g.q_out), else 4.
int p2g_channels(Transfer t, bool fused_positions);
void copy_block_part(const Real* block, int order, int ch, int t, Real* out);

// What they use of the grid: channel sets and tables from SparseGrid + BinTable.
struct MpmGridView {
  Real* a;  // [leaf][512][4]: (m, p) after P2G; (m, v_new) after the grid update
  Real* b;  // PicFlip only: [leaf][512][4]: (-, f) after P2G; (-, v_new - v_old) after the update
  const std::array<std::int32_t, 8>* nbr8;
  const std::uint32_t* bin_start;
  const Vec3i* bin_leaf;
  std::size_t nbins;
  const std::uint32_t* colour_bins;
  const std::uint32_t* colour_start;  // 9 entries
  const std::int32_t* active_leaves;
  std::size_t nactive;
  const Vec3i* leaf_coord;
  // Lagrangian mode only: [leaf][512][4] (m, m q) from p2g_positions, the nodes' current
  // positions q_i (A-ULMPM eq. 12) at which colliders are tested; null: lattice positions.
  const Real* q = nullptr;
  // Lagrangian mode, MLS/APIC: when set, P2G also scatters (m, m q) into it (the node positions
  // of p2g_positions, fused into the momentum scatter: one stencil, an 8-lane block).
  Real* q_out = nullptr;
  // Sleeping blocks (solvers/mpm_sleep.hpp): when set, bin b's particles are
  // [bin_start[b], bin_end[b]) in P2G and G2P (bin_end[b] = bin_start[b]: the bin sleeps).
  const std::uint32_t* bin_end = nullptr;
  // The fused G2P2G: the 27 leaves around each bin's leaf (dx, dy, dz in -1..1, z fastest; -1:
  // none), from which it gathers the bin's dilated block (its particles may have moved up to
  // kG2P2GMargin nodes out of the bin's footprint since the last sort).
  const std::array<std::int32_t, 27>* bin_nbr27 = nullptr;
  std::uint32_t end_of(std::size_t b) const { return bin_end ? bin_end[b] : bin_start[b + 1]; }
  // Distributed P2G: partial blocks of other ranks' bins, grouped by the colour of their bin
  // (imports[import_colour_start[c] .. [c + 1])); P2G adds colour c's before flushing its own
  // colour-c bins, so every node sums the same blocks in the same order as one process.
  const P2GImport* imports = nullptr;
  const std::uint32_t* import_colour_start = nullptr;  // 9 entries
  // Distributed P2G: the blocks p2g_blocks kept. Bin b with kept_slot[b] >= 0 is not scattered
  // again: block kept_slot[b] of `kept` (p2g_block_reals each) is flushed in its colour.
  const std::int32_t* kept_slot = nullptr;
  const Real* kept = nullptr;
  // One process, P2G without colour phases: room for one block per bin (bin b's at
  // b * p2g_block_reals(order, p2g_channels(...))) and the grid's leaf_bins (SparseGrid). When
  // both are set (and no imports or kept blocks), P2G scatters every bin into its block in one
  // balanced loop, and each active leaf's blocks are summed in colour order by the thread that
  // completes the last of them: the colour phases' sums, bit for bit, in one loop instead of eight.
  Real* blocks = nullptr;
  const std::array<std::int32_t, 8>* leaf_bins = nullptr;
};

class SparseGrid;
// The view of `grid`'s tables and `bins` with the given channel sets (b may be null).
MpmGridView make_grid_view(const SparseGrid& grid, const BinTable& bins, Real* a, Real* b);

struct MpmStepParams {
  Transfer transfer = Transfer::Mls;
  int order = 2;  // B-spline order: 2 quadratic, 3 cubic
  Real dx = Real(0.01);
  Real dt = Real(1e-4);
  Real flip_alpha = Real(0.95);
  Vec3 gravity = Vec3(0, Real(-9.81), 0);
  Real time = 0;  // time at the start of the substep (for moving colliders)
  const MaterialParams* materials = nullptr;
  const Collider* colliders = nullptr;
  int ncolliders = 0;
  // The split (dt-free) grid of the fused G2P2G (every transfer): P2G scatters (m, m v + m C o)
  // into a and the stress force (without dt) into b; grid_update forms (p + dt f) / m + dt g.
  bool split = false;
  // g2p and g2p_dilated: each bin's particles then meet the colliders at time + dt
  // (collide_particle, the particle collisions of collide_particles: the same bits), as in g2p2g.
  bool collide = false;
  // g2p, g2p_dilated and g2p2g: when set, *check = the stability check (kernels/
  // stability_check.hpp) of every particle after the kernel's updates, with check_limits.
  StabilityCheck* check = nullptr;
  StabilityLimits check_limits;
};

// Zeroes the transfer channels of the active leaves.
void grid_clear(const exec::Space& space, const MpmGridView& g, const MpmStepParams& prm);
// Particle -> grid scatter of mass, momentum and (per scheme) force.
void p2g(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
         const MpmStepParams& prm);
// Distributed P2G: the P2G block of each listed bin, handed to take(k, block, ch) for bins[k]
// (called on the exec threads, one bin at a time each; explicit transfers, Eulerian or
// Lagrangian (p.X_ref), with g.q_out: the fused node positions in lanes 4..7 as in p2g) and
// stored at keep + k * p2g_block_reals(order, ch) for p2g's flush (g.kept).
void p2g_blocks(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                const MpmStepParams& prm, const std::uint32_t* bins, std::size_t nbins, Real* keep,
                const std::function<void(std::size_t, const Real*, int)>& take);
// Zeroes the active leaves of a [leaf][512][4] array (g.q_out before a fused P2G).
void clear_node4(const exec::Space& space, const MpmGridView& g, Real* out);
// Lagrangian mode: scatters (m_p, m_p (x_p + F_s (X_i - X_p))) into `out` ([leaf][512][4]),
// the mass-weighted affine extrapolation of the current positions to the reference grid nodes
// (A-ULMPM eq. 12, with the APIC-style first-order term so that affine motion is exact).
void p2g_positions(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                   const MpmStepParams& prm, Real* out);
// Momentum -> velocity, forces, gravity, colliders, per active leaf.
void grid_update(const exec::Space& space, const MpmGridView& g, const MpmStepParams& prm);
// Applies the colliders to the grid velocities (a = (m, v) after grid_update), keeping PIC/FLIP's
// b = v_new - v_old consistent: the implicit solver's final pass (friction, separation).
void grid_apply_colliders(const exec::Space& space, const MpmGridView& g, const MpmStepParams& prm);
// Grid -> particle gather of v (and C), F update and advection.
void g2p(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
         const MpmStepParams& prm);

// The fused G2P2G (Wang et al. 2020; explicit, Eulerian): one pass over each bin's particles,
// g2p, the particle collisions with prm's colliders at prm.time + prm.dt, the material update
// (mu, when not null), then the split (dt-free, MpmStepParams::split) scatter of the updated
// particles into the bin's dilated block at blocks + b * g2p2g_block_reals(order): the bin
// leaf's (8 + order)^3 nodes and kG2P2GMargin more on every side, 8 lanes ((m, m v + m C o),
// (0, f)). far[b] = 1 when a particle of bin b moved out of its block (its scatter is skipped).
// g2p2g_flush then sums the blocks into the next grid's leaves (a and b), each leaf its listed
// blocks in list order (bin << 5 | t for the leaf at the bin's leaf + (t / 9 - 1, t / 3 % 3 - 1,
// t % 3 - 1), items[start[li] .. start[li + 1]) for active leaf li): bitwise on any thread count.
constexpr int kG2P2GMargin = 1;
std::size_t g2p2g_block_reals(int order);
void g2p2g(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
           const MpmStepParams& prm, const MaterialUpdateParams* mu, Real* blocks,
           std::uint8_t* far);
void g2p2g_flush(const exec::Space& space, const MpmGridView& g, int order, const Real* blocks,
                 const std::uint32_t* start, const std::uint32_t* items);

// The two passes between sorts (MpmSolver's re-sort when needed, explicit and Eulerian): the
// particles stay in the bins of the last sort while their stencils fit the bins' dilated blocks
// (kG2P2GMargin more nodes on every side, as the fused pass's).
// p2g_dilated: each bin's particles into its dilated block at blocks + b * dilated_block_reals(
// order, p2g_channels(transfer, false)) (the two passes' lanes and values: (m, p), PIC/FLIP's
// force in lanes 4-7), all bins in one loop; each active leaf li of g is overwritten with the
// parts listed for it (start / items as g2p2g_flush) in list order, by the thread completing the
// last block reaching it (target[b * 27 + t]: the active index of the leaf at bin b's leaf +
// (t / 9 - 1, t / 3 % 3 - 1, t % 3 - 1), or -1): bitwise on any thread count. far[b] = 1 when a
// particle of bin b lies outside the block (not scattered: the grid is then incomplete).
// g2p_dilated: g2p from each bin's dilated block (g.bin_nbr27), far[b] = 1 when a particle of
// bin b ends outside its block.
std::size_t dilated_block_reals(int order, int ch);
void p2g_dilated(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                 const MpmStepParams& prm, Real* blocks, const std::uint32_t* start,
                 const std::uint32_t* items, const std::int32_t* target, std::uint8_t* far);
void g2p_dilated(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                 const MpmStepParams& prm, std::uint8_t* far);
// Every active leaf li < g.nactive (g.active_leaves) = the parts of the dilated blocks (ch lanes:
// 4, or 8 with PIC/FLIP's force) listed for it (start / items as g2p2g_flush), in list order: the
// sums of p2g_dilated without its scatter (a distributed run's owned leaves, solvers/
// mpm_distributed.cpp: its bins' blocks and other ranks' parts copied into blocks of their own).
void sum_dilated_leaves(const exec::Space& space, const MpmGridView& g, int order, int ch,
                        const Real* blocks, const std::uint32_t* start, const std::uint32_t* items);
// The part of a dilated block in the leaf at the bin's leaf + (t / 9 - 1, t / 3 % 3 - 1,
// t % 3 - 1) (t = 0..26): its nodes n0 <= n < n1 of that leaf, their count, and the part copied
// between a dilated block (ch lanes) and `part` (the nodes in leaf order, z fastest, ch each).
void dilated_part_range(int order, int t, int* n0, int* n1);
int dilated_part_nodes(int order, int t);
void copy_dilated_part(Real* block, int order, int ch, int t, Real* part, bool to_block);

// The kernels above for one instruction set: mpm_transfers.cpp is compiled once per vector width
// (core/exec/simd.hpp), each copy in its namespace with one of these tables; the functions above
// call the table of exec::simd_path() (kernels/simd_dispatch.cpp). A new kernel of that file
// goes in the table too.
struct MpmKernelTable {
  using Grid = void (*)(const exec::Space&, const MpmGridView&, const MpmStepParams&);
  using Particles = void (*)(const exec::Space&, const MpmParticleView&, const MpmGridView&,
                             const MpmStepParams&);
  Grid grid_clear;
  Particles p2g;
  void (*clear_node4)(const exec::Space&, const MpmGridView&, Real*);
  void (*p2g_positions)(const exec::Space&, const MpmParticleView&, const MpmGridView&,
                        const MpmStepParams&, Real*);
  Grid grid_update;
  Grid grid_apply_colliders;
  Particles g2p;
  void (*p2g_blocks)(const exec::Space&, const MpmParticleView&, const MpmGridView&,
                     const MpmStepParams&, const std::uint32_t*, std::size_t, Real*,
                     const std::function<void(std::size_t, const Real*, int)>&);
  void (*g2p2g)(const exec::Space&, const MpmParticleView&, const MpmGridView&,
                const MpmStepParams&, const MaterialUpdateParams*, Real*, std::uint8_t*);
  void (*g2p2g_flush)(const exec::Space&, const MpmGridView&, int, const Real*,
                      const std::uint32_t*, const std::uint32_t*);
  void (*p2g_dilated)(const exec::Space&, const MpmParticleView&, const MpmGridView&,
                      const MpmStepParams&, Real*, const std::uint32_t*, const std::uint32_t*,
                      const std::int32_t*, std::uint8_t*);
  void (*g2p_dilated)(const exec::Space&, const MpmParticleView&, const MpmGridView&,
                      const MpmStepParams&, std::uint8_t*);
  void (*sum_dilated_leaves)(const exec::Space&, const MpmGridView&, int, int, const Real*,
                             const std::uint32_t*, const std::uint32_t*);
};

}  // namespace amalgam
