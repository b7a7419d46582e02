// The particles' elastic energy as a stiffness term of the implicit system (enriched MPM
// eqs. 14-19): H du and diag(H) over the grid DOFs through the kernels of kernels/implicit_mpm.
#pragma once

#include "kernels/implicit_mpm.hpp"
#include "solvers/implicit_system.hpp"

namespace amalgam {

class MpmElasticTerm final : public ImplicitTerm {
 public:
  MpmElasticTerm(const MpmParticleView& p, const MpmGridView& g, const ImplicitKernelParams& prm,
                 const ParticleHessian* hess)
      : p_(p), g_(g), prm_(prm), hess_(hess) {}
  void add_hessian_action(const exec::Space& space, const Real* du, Real scale,
                          Real* out) const override {
    mpm_hessian_action(space, p_, g_, prm_, hess_, du, scale, out);
  }
  void add_hessian_diagonal(const exec::Space& space, Real scale, Real* diag) const override {
    mpm_hessian_diagonal(space, p_, g_, prm_, hess_, scale, diag);
  }

 private:
  MpmParticleView p_;
  MpmGridView g_;
  ImplicitKernelParams prm_;
  const ParticleHessian* hess_;
};

}  // namespace amalgam
