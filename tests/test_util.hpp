// Shared test helpers: the backend/thread configurations every kernel test runs on.
#pragma once

#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"

namespace amalgam::test {

struct Config {
  exec::Backend backend;
  int threads;
  std::string name() const {
    return std::string(exec::backend_name(backend)) + "_" + std::to_string(threads);
  }
};

// Backends the tests may use: all, or those named in AMALGAM_TEST_BACKENDS (e.g. "serial,tbb":
// scripts/test_tsan.sh leaves OpenMP out because ThreadSanitizer cannot see libgomp's barriers).
inline bool backend_enabled(exec::Backend b) {
  const char* e = std::getenv("AMALGAM_TEST_BACKENDS");
  return !e || std::strstr(e, exec::backend_name(b)) != nullptr;
}
// The parallel backend for single-configuration tests: OpenMP unless excluded, then TBB, then
// std::threads.
inline exec::Backend parallel_backend() {
  if (backend_enabled(exec::Backend::OpenMP)) return exec::Backend::OpenMP;
  return backend_enabled(exec::Backend::TBB) ? exec::Backend::TBB : exec::Backend::Threads;
}

// Serial first (the reference), then OpenMP and TBB with 1 and 2 threads, Kokkos when built (its
// host space's concurrency: 1 with Debian's Serial-only Kokkos), and std::threads with 2 when
// AMALGAM_TEST_BACKENDS names them.
inline std::vector<Config> all_configs() {
  std::vector<Config> out;
  for (const Config& c : std::vector<Config>{{exec::Backend::Serial, 1},
                                             {exec::Backend::OpenMP, 1},
                                             {exec::Backend::OpenMP, 2},
                                             {exec::Backend::TBB, 1},
                                             {exec::Backend::TBB, 2},
                                             {exec::Backend::Kokkos, 1},
                                             {exec::Backend::Threads, 2}})
    if (!exec::backend_compiled(c.backend))
      continue;
    else if (c.backend == exec::Backend::Serial ||
             (c.backend == exec::Backend::Threads
                  ? std::getenv("AMALGAM_TEST_BACKENDS") && backend_enabled(c.backend)
                  : backend_enabled(c.backend)))
      out.push_back(c);
  return out;
}

template <class T>
bool bitwise_equal(const T* a, const T* b, size_t n) {
  return std::memcmp(a, b, n * sizeof(T)) == 0;
}

}  // namespace amalgam::test
