#include "solvers/configuration_maps.hpp"

#include <array>
#include <cmath>

#include "core/dist/comm.hpp"
#include "core/errors.hpp"

namespace amalgam {

const char* configuration_update_name(ConfigurationUpdate u) {
  switch (u) {
    case ConfigurationUpdate::Eulerian:
      return "eulerian";
    case ConfigurationUpdate::TotalLagrangian:
      return "total_lagrangian";
    case ConfigurationUpdate::Adaptive:
      return "adaptive";
  }
  return "?";
}

ConfigurationAttributes ConfigurationAttributes::add_to(ParticleSet& ps) {
  ConfigurationAttributes a;
  a.X_s = ps.add("X_s", AttrType::Real, 3);
  a.F_s = ps.add("F_s", AttrType::Real, 9);
  a.F_0s = ps.add("F_0s", AttrType::Real, 9);
  a.object = ps.add("object", AttrType::Int32, 1);
  return a;
}

int ConfigurationMaps::add_object(const ConfigurationPolicy& policy, std::size_t particles) {
  if (int(policy_.size()) >= kMaxObjects)
    throw InputError("at most " + std::to_string(kMaxObjects) +
                     " objects can keep their own configuration map");
  policy_.push_back(policy);
  stats_.push_back({});
  count_.push_back(particles);
  return int(policy_.size()) - 1;
}

bool ConfigurationMaps::decide(const exec::Space& space, const ParticleSet& ps,
                               const ConfigurationAttributes& a, std::vector<std::uint8_t>& reset,
                               bool distributed) {
  const int nobj = object_count();
  reset.assign(size_t(nobj), 0);
  bool adaptive = false, any = false;
  for (int k = 0; k < nobj; ++k) {
    adaptive |= policy_[size_t(k)].update == ConfigurationUpdate::Adaptive;
    if (policy_[size_t(k)].update == ConfigurationUpdate::Eulerian) reset[size_t(k)] = any = true;
  }
  if (!adaptive) return any;
  using Counts = std::array<std::uint64_t, kMaxObjects>;
  std::array<Real, kMaxObjects> eps{};
  for (int k = 0; k < nobj; ++k) eps[size_t(k)] = policy_[size_t(k)].epsilon;
  const Mat3* Fs = ps.mat3(a.F_s);
  const std::int32_t* obj = ps.int32(a.object);
  // eq. 33: dJ_p = |J_p^{s(n+1)} - J_p^{ss}|, J^{ss} = 1.
  Counts marked = exec::parallel_reduce(
      space, "aul.criterion", exec::Index(ps.size()), Counts{},
      [=](exec::Index i, Counts& acc) {
        const Real dJ = std::abs(Fs[i].determinant() - Real(1));
        if (!(dJ < eps[size_t(obj[i])])) ++acc[size_t(obj[i])];
      },
      [](Counts x, const Counts& y) {
        for (size_t k = 0; k < x.size(); ++k) x[k] += y[k];
        return x;
      });
  if (distributed) {  // every rank's counts (integers: the sum is exact in any order)
    const dist::Comm& comm = dist::Comm::world();
    const std::vector<std::uint64_t> all = dist::from_bytes<std::uint64_t>(comm.allgather(
        dist::as_bytes(std::vector<std::uint64_t>(marked.begin(), marked.end())), nullptr));
    marked = Counts{};
    for (size_t i = 0; i < all.size(); ++i) marked[i % marked.size()] += all[i];
  }
  for (int k = 0; k < nobj; ++k) {
    const ConfigurationPolicy& p = policy_[size_t(k)];
    if (p.update != ConfigurationUpdate::Adaptive || count_[size_t(k)] == 0) continue;
    if (double(marked[size_t(k)]) >= double(p.eta) * double(count_[size_t(k)]))
      reset[size_t(k)] = any = true;
  }
  return any;
}

void ConfigurationMaps::reset(const exec::Space& space, ParticleSet& ps,
                              const ConfigurationAttributes& a, ParticleSet::Id x_id,
                              ParticleSet::Id F_id, ParticleSet::Id C_id, Real dx,
                              const std::vector<std::uint8_t>& reset) {
  std::array<Vec3, kMaxObjects> offset;
  std::array<std::uint8_t, kMaxObjects> flag{};
  for (int k = 0; k < object_count(); ++k) {
    offset[size_t(k)] = lane_offset(k, dx);
    flag[size_t(k)] = reset[size_t(k)];
  }
  Vec3* Xs = ps.vec3(a.X_s);
  Mat3* Fs = ps.mat3(a.F_s);
  Mat3* F0s = ps.mat3(a.F_0s);
  const std::int32_t* obj = ps.int32(a.object);
  const Vec3* x = ps.vec3(x_id);
  const Mat3* F = ps.mat3(F_id);
  Mat3* C = C_id >= 0 ? ps.mat3(C_id) : nullptr;  // PIC/FLIP without viscosity: no C
  exec::parallel_for(space, "aul.reset_configuration", exec::Index(ps.size()), [=](exec::Index i) {
    const size_t k = size_t(obj[i]);
    if (!flag[k]) return;
    if (C) C[i] = C[i] * Fs[i].inverse();  // grad_{new} v = grad_s v (F^{sn})^{-1}
    Xs[i] = x[i] + offset[k];
    F0s[i] = F[i];
    Fs[i].setIdentity();
  });
}

void ConfigurationMaps::account(const std::vector<std::uint8_t>& reset, double check,
                                double seconds) {
  std::size_t total = 0, all = 0;
  for (size_t k = 0; k < policy_.size(); ++k) {
    ++stats_[k].steps;
    all += count_[k];
    if (reset.size() > k && reset[k]) total += count_[k];
  }
  for (size_t k = 0; k < policy_.size(); ++k)
    stats_[k].check_seconds += all ? check * double(count_[k]) / double(all) : 0.0;
  for (size_t k = 0; k < policy_.size(); ++k) {
    if (reset.size() <= k || !reset[k]) continue;
    ++stats_[k].updates;
    stats_[k].update_seconds += total ? seconds * double(count_[k]) / double(total) : 0.0;
  }
}

}  // namespace amalgam
