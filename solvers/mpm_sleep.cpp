#include "solvers/mpm_sleep.hpp"

#include <algorithm>
#include <cmath>
#include <unordered_map>

#include "core/dist/comm.hpp"
#include "solvers/mpm_sources.hpp"

namespace amalgam {

namespace {
std::uint64_t leaf_key(const Vec3i& c) {
  const auto u = [](int v) { return std::uint64_t(std::uint32_t(v + (1 << 20))) & 0x1fffffULL; };
  return (u(c[0]) << 42) | (u(c[1]) << 21) | u(c[2]);
}
bool moving(const Collider& c, double t) {
  if (double(c.until) < t) return false;  // released
  return c.velocity.squaredNorm() > 0 || c.omega.squaredNorm() > 0 || !c.keys.empty() || c.drive ||
         (c.field && c.field->deforming());  // a deforming sequence moves where it grows
}
}  // namespace

MpmSleep::MpmSleep(ParticleSet& ps, const SleepSettings& s) : s_(s) {
  rest_ = ps.add("rest_time", AttrType::Real, 1);
  asleep_ = ps.add("asleep", AttrType::Int32, 1);
}

void MpmSleep::decide(const exec::Space& space, ParticleSet& ps, const MpmAttributes& a,
                      const BinTable& bins, Real dx, double time, const Collider* colliders,
                      int ncolliders, const std::vector<EmitterSpec>& emitters, bool distributed) {
  const std::size_t nb = bins.count();
  const std::uint32_t* start = bins.start.data();
  const Real* rest = ps.real(rest_);
  const Real need = s_.time;
  rested_.assign(nb, 0);
  std::uint8_t* rested = rested_.data();
  exec::parallel_for(space, "sleep.rested", exec::Index(nb), [=](exec::Index b) {
    bool r = true;
    for (std::uint32_t q = start[b]; q < start[b + 1] && r; ++q) r = rest[q] >= need;
    rested[b] = r ? 1 : 0;
  });
  const double halo = s_.halo > 0 ? double(s_.halo) : 2.0 * double(dx);
  const double leaf = double(kLeafDim) * double(dx);
  const int reach = int(std::ceil(halo / leaf));
  // Whether each bin (by leaf) has rested; distributed, the bins of every rank (a bin's
  // neighbours within the halo may live on other ranks), so each rank decides as one process.
  std::vector<std::uint64_t> keyed(nb);
  for (std::size_t b = 0; b < nb; ++b) keyed[b] = (leaf_key(bins.leaf[b]) << 1) | rested[b];
  if (distributed)
    keyed = dist::from_bytes<std::uint64_t>(
        dist::Comm::world().allgather(dist::as_bytes(keyed), nullptr));
  std::unordered_map<std::uint64_t, std::uint8_t> index;
  index.reserve(keyed.size() * 2);
  for (const std::uint64_t k : keyed) index.emplace(k >> 1, std::uint8_t(k & 1));
  sleeps_.assign(nb, 0);
  for (std::size_t b = 0; b < nb; ++b) {
    if (!rested[b]) continue;
    bool ok = true;
    const Vec3i c = bins.leaf[b];
    for (int i = -reach; i <= reach && ok; ++i)
      for (int j = -reach; j <= reach && ok; ++j)
        for (int k = -reach; k <= reach && ok; ++k) {
          const auto it = index.find(leaf_key(c + Vec3i(i, j, k)));
          ok = it == index.end() || it->second;
        }
    // The bin's particles lie within the leaf's box (stencil bases) widened by two cells.
    const Vec3d lo = c.cast<double>() * leaf - Vec3d::Constant(2 * double(dx));
    const Vec3d hi = lo + Vec3d::Constant(leaf + 4 * double(dx));
    const Vec3d mid = 0.5 * (lo + hi);
    const double radius = 0.5 * (hi - lo).norm();
    for (int k = 0; k < ncolliders && ok; ++k)
      if (moving(colliders[k], time))
        ok = double(colliders[k].phi(mid.cast<Real>(), Real(time))) > radius + halo;
    for (const EmitterSpec& e : emitters) {
      if (!ok || !(time < e.end)) continue;
      bool near = true;
      for (int d = 0; d < 3; ++d)
        near = near && double(e.min[d]) - halo <= hi[d] && double(e.max[d]) + halo >= lo[d];
      ok = !near;
    }
    sleeps_[b] = ok ? 1 : 0;
  }
  bin_end_.resize(nb);
  std::uint32_t* end = bin_end_.data();
  const std::uint8_t* sleeps = sleeps_.data();
  Vec3* v = ps.vec3(a.v);
  Mat3* C = ps.mat3(a.C);
  Real* rw = ps.real(rest_);
  std::int32_t* flag = ps.int32(asleep_);
  exec::parallel_for(space, "sleep.apply", exec::Index(nb), [=](exec::Index b) {
    if (sleeps[b]) {
      end[b] = start[b];
      for (std::uint32_t q = start[b]; q < start[b + 1]; ++q) {
        v[q] = Vec3::Zero();
        C[q] = Mat3::Zero();
        flag[q] = 1;
      }
    } else {
      end[b] = start[b + 1];
      for (std::uint32_t q = start[b]; q < start[b + 1]; ++q)
        if (flag[q]) {  // woken: it must rest for the whole time again
          flag[q] = 0;
          rw[q] = 0;
        }
    }
  });
}

void MpmSleep::pin_nodes(const exec::Space& space, const SparseGrid& grid, const BinTable& bins,
                         Real* node4) const {
  const std::uint8_t* sleeps = sleeps_.data();
  const auto* nbr8 = grid.nbr8().data();
  const Vec3i* coord = grid.leaf_coords().data();
  const Vec3i* bin_leaf = bins.leaf.data();
  exec::parallel_for(space, "sleep.pin", exec::Index(bins.count()), [=](exec::Index b) {
    if (!sleeps[b]) return;
    for (int n = 0; n < 8; ++n) {
      const std::int32_t l = nbr8[b][std::size_t(n)];
      if (l < 0 || coord[l] != bin_leaf[b]) continue;
      Real* d = node4 + std::size_t(l) * kLeafNodes * 4;
      for (int i = 0; i < kLeafNodes; ++i) d[4 * i + 1] = d[4 * i + 2] = d[4 * i + 3] = 0;
    }
  });
}

void MpmSleep::rest(const exec::Space& space, ParticleSet& ps, const MpmAttributes& a,
                    Real dt) const {
  const Vec3* v = ps.vec3(a.v);
  const Mat3* C = ps.mat3(a.C);
  Real* r = ps.real(rest_);
  const std::int32_t* flag = ps.int32(asleep_);
  const Real s2 = s_.speed * s_.speed, e2 = s_.strain_rate * s_.strain_rate;
  exec::parallel_for(space, "sleep.rest", exec::Index(ps.size()), [=](exec::Index p) {
    if (flag[p]) return;
    const Mat3 D = Real(0.5) * (C[p] + C[p].transpose());
    r[p] = (v[p].squaredNorm() < s2 && D.squaredNorm() < e2) ? r[p] + dt : Real(0);
  });
}

std::size_t MpmSleep::sleeping(const ParticleSet& ps) const {
  const std::int32_t* flag = ps.int32(asleep_);
  std::size_t n = 0;
  for (std::size_t p = 0; p < ps.size(); ++p) n += std::size_t(flag[p] != 0);
  return n;
}

}  // namespace amalgam
