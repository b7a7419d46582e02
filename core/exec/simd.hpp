// Vector width chosen at run time (issue 31, item 4). The hot kernel files are compiled once per
// instruction set (kernels/CMakeLists.txt, amalgam_simd_variants): the portable baseline (x86-64,
// SSE2), AVX2 (-mavx2) and AVX-512 (-mavx512f -mavx512vl -mavx512bw -mavx512dq -mfma: Eigen
// refuses AVX-512 without FMA; BW for byte lanes at 512 bits),
// always with -ffp-contract=off (GCC would otherwise contract a * b + c into an FMA). Each compilation puts the file's
// kernels in its own namespace (AMALGAM_ISA below: isa_baseline, isa_avx2, isa_avx512) and
// exports a table of entry points; every other symbol of a variant object is made local after a
// relocatable link (ld -r --force-group-allocation; objcopy), so the variants' copies of inline
// Eigen / standard-library / project functions never replace the baseline's in the final link.
// The public kernel functions pick the table of simd_path() on each call.
//
// The path is, in order: set_simd_path(), the environment variable AMALGAM_SIMD
// (baseline|avx2|avx512|auto), or the widest one both compiled and supported by the CPU
// (__builtin_cpu_supports, which also checks that the OS saves the wide registers).
//
// Results are bitwise identical on every path: the kernels are element-wise IEEE operations on
// explicit vectors (core/math/simd4.hpp, lanes.hpp), with no contraction and no reassociation,
// and the particle lanes of lanes.hpp compute each particle alone (tests/test_simd.cpp compares
// the kernels and a CLI scene on every path the CPU has).
#pragma once

#include <string>
#include <vector>

// The namespace of the kernels of the file being compiled: set by the build for the variants.
#ifndef AMALGAM_ISA
#define AMALGAM_ISA isa_baseline
#endif

namespace amalgam::exec {

enum class SimdPath { Baseline, Avx2, Avx512 };

// "baseline", "avx2", "avx512".
const char* simd_path_name(SimdPath p);
// The compiler flags of the path, e.g. "-mavx2" ("" for baseline).
const char* simd_path_flags(SimdPath p);
// Whether this binary holds the path's kernels (AMALGAM_SIMD_DISPATCH=ON on x86-64, not native).
bool simd_path_compiled(SimdPath p);
// Compiled and the CPU (and OS) can run it.
bool simd_path_supported(SimdPath p);
// The paths simd_path_supported, baseline first.
std::vector<SimdPath> supported_simd_paths();
// The widest supported path.
SimdPath best_simd_path();
// Parses "baseline", "avx2", "avx512" or "auto" (the best path), case-insensitive; throws
// std::invalid_argument for another name or a path this CPU or build cannot run, saying why.
SimdPath parse_simd_path(const std::string& name);
// The path the kernels take now (first call: AMALGAM_SIMD if set, else the best; an invalid
// AMALGAM_SIMD throws std::invalid_argument naming the variable).
SimdPath simd_path();
// Forces the path (tests, benchmarks, `--simd`); throws std::invalid_argument if unsupported.
void set_simd_path(SimdPath p);
// "avx512 (-mavx512f -mavx512vl -mavx512bw -mavx512dq -mfma; compiled: baseline avx2 avx512;
// CPU runs: baseline avx2 avx512)",
// for `amalgam info` and the benchmark header.
std::string simd_description();

// The entry-point table of the current path among a kernel file's compiled variants (null
// pointers for variants not compiled; NotDeduced: a nullptr argument does not deduce Table).
template <class T>
struct NotDeduced {
  using type = T;
};
template <class Table>
const Table& pick_simd(const Table& baseline, const typename NotDeduced<Table>::type* avx2,
                       const typename NotDeduced<Table>::type* avx512) {
  switch (simd_path()) {
    case SimdPath::Avx512:
      if (avx512) return *avx512;
      break;
    case SimdPath::Avx2:
      if (avx2) return *avx2;
      break;
    case SimdPath::Baseline:
      break;
  }
  return baseline;
}

}  // namespace amalgam::exec

// Declares a kernel file's table `name` of type `Type` in every variant namespace (in namespace
// amalgam), and picks the current path's: AMALGAM_SIMD_PICK(name).
#define AMALGAM_SIMD_DECLARE(Type, name) \
  namespace isa_baseline {               \
  extern const Type name;                \
  }                                      \
  namespace isa_avx2 {                   \
  extern const Type name;                \
  }                                      \
  namespace isa_avx512 {                 \
  extern const Type name;                \
  }
#ifdef AMALGAM_SIMD_AVX2
#define AMALGAM_SIMD_AVX2_TABLE(name) (&isa_avx2::name)
#else
#define AMALGAM_SIMD_AVX2_TABLE(name) nullptr
#endif
#ifdef AMALGAM_SIMD_AVX512
#define AMALGAM_SIMD_AVX512_TABLE(name) (&isa_avx512::name)
#else
#define AMALGAM_SIMD_AVX512_TABLE(name) nullptr
#endif
#define AMALGAM_SIMD_PICK(name)                                                 \
  ::amalgam::exec::pick_simd(isa_baseline::name, AMALGAM_SIMD_AVX2_TABLE(name), \
                             AMALGAM_SIMD_AVX512_TABLE(name))
