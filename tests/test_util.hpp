// Shared test helpers: the backend/thread configurations every kernel test runs on.
#pragma once

#include <cstring>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"

namespace amalgam::test {

struct Config {
  exec::Backend backend;
  int threads;
  std::string name() const { return std::string(exec::backend_name(backend)) + "_" + std::to_string(threads); }
};

// Serial first (the reference), then OpenMP and TBB with 1 and 2 threads.
inline std::vector<Config> all_configs() {
  return {{exec::Backend::Serial, 1}, {exec::Backend::OpenMP, 1}, {exec::Backend::OpenMP, 2},
          {exec::Backend::TBB, 1},    {exec::Backend::TBB, 2}};
}

template <class T>
bool bitwise_equal(const T* a, const T* b, size_t n) {
  return std::memcmp(a, b, n * sizeof(T)) == 0;
}

}  // namespace amalgam::test
