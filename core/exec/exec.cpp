// Backends of the exec layer. The only file of the project with OpenMP pragmas and TBB calls
// (Kokkos calls are in exec_kokkos.cpp, compiled when CMake found Kokkos).
#include "core/exec/exec.hpp"
#include "core/exec/cpus.hpp"

#include <omp.h>
#include <sched.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <stdexcept>
#include <thread>

namespace amalgam::exec {

namespace detail {
#ifdef AMALGAM_HAVE_KOKKOS
// exec_kokkos.cpp
void kokkos_run_chunks(Index nchunks, ChunkFn fn, void* ctx);
int kokkos_concurrency();
std::string kokkos_version();
#endif

struct BackendState {
  Backend backend;
  int threads;
  // Fixes TBB's concurrency to `threads`: the TBB backend's kernels, and library code run through
  // with_thread_limit on every backend.
  std::unique_ptr<tbb::task_arena> arena;
};

void run_chunks(const BackendState& s, Index nchunks, ChunkFn fn, void* ctx) {
  // Kokkos runs even one thread through Kokkos, so its path is the one measured and tested.
  if (s.backend != Backend::Kokkos &&
      (nchunks == 1 || s.threads == 1 || s.backend == Backend::Serial)) {
    for (Index c = 0; c < nchunks; ++c) fn(ctx, c);
    return;
  }
  switch (s.backend) {
    case Backend::Serial:
      for (Index c = 0; c < nchunks; ++c) fn(ctx, c);
      break;
    case Backend::OpenMP: {
#pragma omp parallel for schedule(dynamic, 1) num_threads(s.threads)
      for (Index c = 0; c < nchunks; ++c) fn(ctx, c);
      break;
    }
    case Backend::TBB:
      s.arena->execute([&] {
        tbb::parallel_for(
            tbb::blocked_range<Index>(0, nchunks, 1),
            [&](const tbb::blocked_range<Index>& r) {
              for (Index c = r.begin(); c != r.end(); ++c) fn(ctx, c);
            },
            tbb::simple_partitioner());
      });
      break;
    case Backend::Threads: {
      std::atomic<Index> next{0};
      auto work = [&] {
        for (Index c = next.fetch_add(1); c < nchunks; c = next.fetch_add(1)) fn(ctx, c);
      };
      std::vector<std::thread> pool;
      for (int t = 1; t < s.threads; ++t) pool.emplace_back(work);
      work();
      for (auto& th : pool) th.join();
      break;
    }
    case Backend::Kokkos:
#ifdef AMALGAM_HAVE_KOKKOS
      detail::kokkos_run_chunks(nchunks, fn, ctx);
#endif
      break;
  }
}
}  // namespace detail

const char* backend_name(Backend b) {
  switch (b) {
    case Backend::Serial:
      return "serial";
    case Backend::OpenMP:
      return "openmp";
    case Backend::TBB:
      return "tbb";
    case Backend::Threads:
      return "threads";
    case Backend::Kokkos:
      return "kokkos";
  }
  return "?";
}

Backend parse_backend(const std::string& name) {
  std::string s = name;
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return std::tolower(c); });
  if (s == "serial") return Backend::Serial;
  if (s == "openmp" || s == "omp") return Backend::OpenMP;
  if (s == "tbb") return Backend::TBB;
  if (s == "threads") return Backend::Threads;
  if (s == "kokkos") {
    if (!backend_compiled(Backend::Kokkos))
      throw std::invalid_argument(
          "backend 'kokkos' is not in this build (CMake did not find Kokkos; install "
          "libtrilinos-kokkos-dev and reconfigure)");
    return Backend::Kokkos;
  }
  throw std::invalid_argument("unknown backend '" + name +
                              "' (expected serial, openmp, tbb, threads or kokkos)");
}

bool backend_compiled(Backend b) {
#ifdef AMALGAM_HAVE_KOKKOS
  (void)b;
  return true;
#else
  return b != Backend::Kokkos;
#endif
}

std::vector<Backend> available_backends() {
  std::vector<Backend> out{Backend::Serial, Backend::OpenMP, Backend::TBB};
  if (backend_compiled(Backend::Kokkos)) out.push_back(Backend::Kokkos);
  return out;
}

std::string kokkos_version() {
#ifdef AMALGAM_HAVE_KOKKOS
  return detail::kokkos_version();
#else
  return "";
#endif
}

int hardware_threads() {
  const unsigned n = std::thread::hardware_concurrency();
  return n == 0 ? 1 : static_cast<int>(n);
}

int usable_threads() {
#ifdef __linux__
  cpu_set_t set;
  CPU_ZERO(&set);
  if (sched_getaffinity(0, sizeof set, &set) == 0) {
    const int n = CPU_COUNT(&set);
    if (n > 0) return n;
  }
#endif
  return hardware_threads();
}

Space::Space(Backend backend, int threads, Profiler* profiler)
    : backend_(backend), threads_(backend == Backend::Serial ? 1 : threads), profiler_(profiler) {
  if (threads < 1)
    throw std::invalid_argument("thread count must be >= 1, got " + std::to_string(threads));
  if (!backend_compiled(backend))
    throw std::invalid_argument("backend 'kokkos' is not in this build");
#ifdef AMALGAM_HAVE_KOKKOS
  if (backend_ == Backend::Kokkos) threads_ = std::min(threads_, detail::kokkos_concurrency());
#endif
  state_ = std::make_shared<detail::BackendState>();
  state_->backend = backend_;
  state_->threads = threads_;
  state_->arena = std::make_unique<tbb::task_arena>(threads_);
}

void with_thread_limit(const Space& space, const std::function<void()>& fn) {
  space.state().arena->execute(fn);
}

std::string Space::describe() const {
  return std::string(backend_name(backend_)) + " x" + std::to_string(threads_);
}

}  // namespace amalgam::exec
