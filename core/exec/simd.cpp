#include "core/exec/simd.hpp"

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cstdlib>
#include <stdexcept>

namespace amalgam::exec {

namespace {

bool cpu_has(SimdPath p) {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_cpu_init();
  switch (p) {
    case SimdPath::Baseline:
      return true;
    case SimdPath::Avx2:
      return __builtin_cpu_supports("avx2");
    case SimdPath::Avx512:
      return __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vl") &&
             __builtin_cpu_supports("avx512bw") && __builtin_cpu_supports("avx512dq") &&
             __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  }
  return false;
#else
  return p == SimdPath::Baseline;
#endif
}

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return std::tolower(c); });
  return s;
}

SimdPath from_environment() {
  const char* e = std::getenv("AMALGAM_SIMD");
  if (!e || !*e) return best_simd_path();
  try {
    return parse_simd_path(e);
  } catch (const std::invalid_argument& err) {
    throw std::invalid_argument(std::string("environment variable AMALGAM_SIMD: ") + err.what());
  }
}

// -1: not chosen yet.
std::atomic<int> g_path{-1};

}  // namespace

const char* simd_path_name(SimdPath p) {
  switch (p) {
    case SimdPath::Baseline:
      return "baseline";
    case SimdPath::Avx2:
      return "avx2";
    case SimdPath::Avx512:
      return "avx512";
  }
  return "?";
}

const char* simd_path_flags(SimdPath p) {
  switch (p) {
    case SimdPath::Baseline:
      return "";
    case SimdPath::Avx2:
      return "-mavx2";
    case SimdPath::Avx512:
      return "-mavx512f -mavx512vl -mavx512bw -mavx512dq -mfma";
  }
  return "";
}

bool simd_path_compiled(SimdPath p) {
  switch (p) {
    case SimdPath::Baseline:
      return true;
    case SimdPath::Avx2:
#ifdef AMALGAM_SIMD_AVX2
      return true;
#else
      return false;
#endif
    case SimdPath::Avx512:
#ifdef AMALGAM_SIMD_AVX512
      return true;
#else
      return false;
#endif
  }
  return false;
}

bool simd_path_supported(SimdPath p) {
  return simd_path_compiled(p) && cpu_has(p);
}

std::vector<SimdPath> supported_simd_paths() {
  std::vector<SimdPath> r;
  for (SimdPath p : {SimdPath::Baseline, SimdPath::Avx2, SimdPath::Avx512})
    if (simd_path_supported(p)) r.push_back(p);
  return r;
}

SimdPath best_simd_path() {
  return supported_simd_paths().back();
}

SimdPath parse_simd_path(const std::string& name) {
  const std::string s = lower(name);
  SimdPath p;
  if (s == "auto") return best_simd_path();
  if (s == "baseline")
    p = SimdPath::Baseline;
  else if (s == "avx2")
    p = SimdPath::Avx2;
  else if (s == "avx512")
    p = SimdPath::Avx512;
  else
    throw std::invalid_argument("unknown SIMD path '" + name +
                                "' (expected baseline, avx2, avx512 or auto)");
  if (!simd_path_compiled(p))
    throw std::invalid_argument(std::string("SIMD path '") + simd_path_name(p) +
                                "' is not in this build (AMALGAM_SIMD_DISPATCH=OFF, a native "
                                "build or not x86-64)");
  if (!cpu_has(p))
    throw std::invalid_argument(std::string("SIMD path '") + simd_path_name(p) + "' needs " +
                                simd_path_flags(p) + " instructions this CPU does not have");
  return p;
}

SimdPath simd_path() {
  int p = g_path.load(std::memory_order_relaxed);
  if (p < 0) {
    p = int(from_environment());
    g_path.store(p, std::memory_order_relaxed);
  }
  return SimdPath(p);
}

void set_simd_path(SimdPath p) {
  if (!simd_path_supported(p)) parse_simd_path(simd_path_name(p));  // throws, saying why
  g_path.store(int(p), std::memory_order_relaxed);
}

std::string simd_description() {
  const SimdPath p = simd_path();
  std::string s = simd_path_name(p);
  s += p == SimdPath::Baseline ? " (x86-64 baseline, SSE2" : std::string(" (") + simd_path_flags(p);
  s += "; compiled:";
  for (SimdPath q : {SimdPath::Baseline, SimdPath::Avx2, SimdPath::Avx512})
    if (simd_path_compiled(q)) s += std::string(" ") + simd_path_name(q);
  s += "; CPU runs:";
  for (SimdPath q : supported_simd_paths()) s += std::string(" ") + simd_path_name(q);
  s += ")";
  return s;
}

}  // namespace amalgam::exec
