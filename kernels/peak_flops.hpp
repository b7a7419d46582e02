// The arithmetic ceiling of a roofline (the benchmark report's "Roofline" section,
// apps/bench_report.cpp; bench/microbench.cpp BM_PeakFlops): independent multiply-add chains on
// the vectors of the current SIMD path (core/exec/simd.hpp), a multiply and a separate add as the
// kernels are compiled (-ffp-contract=off: no FMA), so the peak the kernels could reach.
#pragma once

#include "core/exec/exec.hpp"
#include "core/math/types.hpp"

namespace amalgam {

// Runs `chunks` blocks of `iters` rounds of the chains (parallel_for over the blocks, one block
// per chunk) and returns the floating-point operations executed (2 per multiply-add per lane).
// sink[c] receives block c's sum, so nothing is optimised away.
double peak_flops_run(const exec::Space& space, int chunks, int iters, Real* sink);

struct PeakFlopsTable {
  double (*run)(const exec::Space&, int, int, Real*);
};

}  // namespace amalgam
