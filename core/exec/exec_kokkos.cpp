// The Kokkos backend of the exec layer: the fixed chunks of exec.hpp run as one
// Kokkos::parallel_for over the default host execution space. The only file with Kokkos calls.
// Kokkos is initialised on first use and finalised at exit. Chunks write disjoint memory and
// reductions combine per-chunk partials in chunk order (exec.hpp), so results are bitwise those
// of the native backends whatever the execution space.
#include <Kokkos_Core.hpp>

#include <cstdlib>
#include <mutex>
#include <string>

#include "core/exec/exec.hpp"

namespace amalgam::exec::detail {

namespace {
using HostSpace = Kokkos::DefaultHostExecutionSpace;

void ensure_initialized() {
  static std::once_flag once;
  std::call_once(once, [] {
    if (Kokkos::is_initialized()) return;  // the embedding program owns Kokkos
    Kokkos::InitArguments args;
    args.disable_warnings = true;
    Kokkos::initialize(args);
    std::atexit([] {
      if (Kokkos::is_initialized()) Kokkos::finalize();
    });
  });
}
}  // namespace

void kokkos_run_chunks(Index nchunks, ChunkFn fn, void* ctx) {
  ensure_initialized();
  Kokkos::parallel_for("amalgam.chunks",
                       Kokkos::RangePolicy<HostSpace, Kokkos::IndexType<Index>>(0, nchunks),
                       [fn, ctx](const Index c) { fn(ctx, c); });
  HostSpace().fence();
}

int kokkos_concurrency() {
  ensure_initialized();
  return HostSpace::concurrency();
}

std::string kokkos_version() {
  return "Kokkos " + std::to_string(KOKKOS_VERSION / 10000) + "." +
         std::to_string(KOKKOS_VERSION / 100 % 100) + "." + std::to_string(KOKKOS_VERSION % 100) +
         " (" + HostSpace::name() + ")";
}

}  // namespace amalgam::exec::detail
