#include "kernels/peak_flops.hpp"

#include "core/exec/simd.hpp"
#include "core/math/lanes.hpp"

namespace amalgam {
namespace AMALGAM_ISA {
namespace {

// Independent chains of one vector each: a multiply and its dependent add are 5-8 cycles of
// latency on current x86 cores, and two multiplies and two adds issue per cycle, so the chains
// must outnumber that latency times two. Measured on the 2-core VM (Zen 5, 2026-11-29, GFLOP/s
// at 1 thread, baseline / AVX2 / AVX-512): 12 chains 49 / 100 / 201; 14 chains 54 / 108 / -;
// 16 chains 30 / 60 / 218 (below AVX-512 16 chains spill: 16 registers hold them and nothing
// else); 20 and 24 chains on AVX-512 153 and 170 (spilled or not unrolled).
constexpr int kChains = lanes::kBytes == 64 ? 16 : 14;

double run(const exec::Space& space, int chunks, int iters, Real* sink) {
  using V = lanes::V<Real>;
  constexpr int kN = lanes::kN<Real>;
  exec::parallel_for(
      space, "bench.flops", exec::Index(chunks),
      [=](exec::Index c) {
        V acc[kChains];
        for (int l = 0; l < kChains; ++l)
          acc[l] = lanes::splat(Real(1) + Real(l) * Real(1e-3) + Real(c) * Real(1e-6));
        const V m = lanes::splat(Real(0.999999)), a = lanes::splat(Real(1e-7));
        for (int it = 0; it < iters; ++it)
          for (int l = 0; l < kChains; ++l) acc[l] = acc[l] * m + a;
        Real s = 0;
        for (int l = 0; l < kChains; ++l)
          for (int k = 0; k < kN; ++k) s += acc[l][k];
        sink[c] = s;
      },
      1);
  return 2.0 * double(chunks) * double(iters) * kChains * kN;
}

}  // namespace

extern const PeakFlopsTable peak_flops_kernels;
const PeakFlopsTable peak_flops_kernels = {&run};

}  // namespace AMALGAM_ISA
}  // namespace amalgam
