// Data-parallel execution layer: parallel_for / parallel_reduce / parallel_scan with labels,
// dispatched at run time to the Serial, OpenMP or TBB backend with a chosen thread count (or to
// Kokkos's host execution space, when the build found Kokkos: AMALGAM_KOKKOS).
// Every labelled region is timed by the Space's profiler (when one is attached).
//
// Determinism contract: the work of parallel_for(n) is split into chunks whose boundaries
// depend only on n and the grain, never on the thread count; parallel_reduce combines one
// partial per chunk in chunk order; parallel_scan uses the same fixed chunking. Results are
// therefore bitwise identical on every backend and thread count.
//
// This header holds no OpenMP pragma and no TBB call: backends live in exec.cpp, behind one
// indirect call per chunk.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "core/exec/profiler.hpp"

namespace amalgam::exec {

using Index = std::int64_t;

// Threads: plain std::threads started per parallel region, pulling chunks from an atomic counter.
// Slower (thread start-up per region); it exists so ThreadSanitizer, which cannot see inside the
// uninstrumented libgomp and libtbb of Debian, can check the kernels for data races
// (scripts/test_tsan.sh). Not listed by available_backends().
//
// Kokkos: the chunks run as one Kokkos::parallel_for over Kokkos::DefaultHostExecutionSpace
// (core/exec/exec_kokkos.cpp). Debian's Kokkos 3.4.1 (libtrilinos-kokkos-dev) enables only the
// Serial execution space, so there the backend runs one thread; its thread count is capped at
// the execution space's concurrency. Compiled only when CMake found Kokkos.
enum class Backend { Serial, OpenMP, TBB, Threads, Kokkos };

const char* backend_name(Backend b);
// Parses "serial", "openmp", "tbb", "threads", "kokkos" (case-insensitive); throws
// std::invalid_argument otherwise (also for "kokkos" in a build without it, saying so).
Backend parse_backend(const std::string& name);
// Backends compiled into this build and listed to users, in a fixed order (Kokkos last, when
// built; Threads, a TSan aid, is not listed).
std::vector<Backend> available_backends();
bool backend_compiled(Backend b);
// "Kokkos 3.4.1 (Serial)" when built with Kokkos, "" otherwise.
std::string kokkos_version();
int hardware_threads();

// Per-slot countdowns for "the last arrival does the slot's work" inside a parallel loop (P2G:
// the thread that completes the last block reaching a leaf sums that leaf). arrive(i) is true for
// exactly one caller per slot, the one that brings it to zero; acquire/release ordering makes the
// other arrivals' writes visible to it. The only synchronisation kernels use outside this file.
class Countdowns {
 public:
  explicit Countdowns(std::size_t n) : c_(new std::atomic<int>[n]) {}
  void set(std::size_t i, int n) { c_[i].store(n, std::memory_order_relaxed); }
  bool arrive(std::size_t i) { return c_[i].fetch_sub(1, std::memory_order_acq_rel) == 1; }

 private:
  std::unique_ptr<std::atomic<int>[]> c_;
};

namespace detail {
struct BackendState;
// Type-erased "call body(chunk) for every chunk in [0, nchunks)", one indirect call per chunk.
using ChunkFn = void (*)(void* ctx, Index chunk);
void run_chunks(const BackendState& s, Index nchunks, ChunkFn fn, void* ctx);
}  // namespace detail

// An execution space: a backend, a thread count and an optional profiler. Cheap to copy.
class Space {
 public:
  explicit Space(Backend backend = Backend::Serial, int threads = 1, Profiler* profiler = nullptr);
  Backend backend() const { return backend_; }
  int threads() const { return threads_; }
  Profiler* profiler() const { return profiler_; }
  void set_profiler(Profiler* p) { profiler_ = p; }
  std::string describe() const;
  const detail::BackendState& state() const { return *state_; }

 private:
  Backend backend_;
  int threads_;
  Profiler* profiler_;
  std::shared_ptr<detail::BackendState> state_;
};

// Runs `fn` inside a TBB task arena of the space's thread count (one for Serial), so that library
// code built on TBB that the exec layer does not dispatch itself (OpenVDB's tools: mesh
// voxelisation, point grids) uses at most `space.threads()` threads: `--threads 1` means one
// thread there too. Every OpenVDB tool call of the project goes through it.
void with_thread_limit(const Space& space, const std::function<void()>& fn);

// Chunk size used by parallel_for for n items and a requested grain (0 = automatic). Depends
// only on n and grain, never on threads.
inline Index chunk_size(Index n, Index grain) {
  if (grain > 0) return grain;
  const Index target_chunks = 256;
  Index c = (n + target_chunks - 1) / target_chunks;
  return c < 1 ? 1 : c;
}

// body(begin, end) for the fixed chunks [c * chunk, min(n, (c + 1) * chunk)): for kernels that
// want a whole range at once. Chunks must write disjoint memory.
template <class Body>
void parallel_for_chunks(const Space& space, const char* label, Index n, Index chunk, Body&& body) {
  if (n <= 0) return;
  ScopedRegion region(space.profiler(), label);
  const Index cs = chunk < 1 ? 1 : chunk;
  const Index nchunks = (n + cs - 1) / cs;
  struct Ctx {
    Body* body;
    Index n, cs;
  } ctx{&body, n, cs};
  detail::run_chunks(
      space.state(), nchunks,
      [](void* p, Index c) {
        auto& k = *static_cast<Ctx*>(p);
        const Index b = c * k.cs, e = (b + k.cs < k.n) ? b + k.cs : k.n;
        (*k.body)(b, e);
      },
      &ctx);
}

// body(i) for i in [0, n), in chunks of chunk_size(n, grain). Items must write disjoint memory.
template <class Body>
void parallel_for(const Space& space, const char* label, Index n, Body&& body, Index grain = 0) {
  parallel_for_chunks(space, label, n, chunk_size(n, grain), [&body](Index b, Index e) {
    for (Index i = b; i < e; ++i) body(i);
  });
}

// Deterministic reduction: result = join(...join(join(init, chunk0), chunk1)...), where each
// chunk's partial starts at `init` and folds body(i, acc) in index order.
template <class T, class Body, class Join>
T parallel_reduce(const Space& space, const char* label, Index n, T init, Body&& body, Join&& join,
                  Index grain = 0) {
  if (n <= 0) return init;
  ScopedRegion region(space.profiler(), label);
  const Index cs = chunk_size(n, grain);
  const Index nchunks = (n + cs - 1) / cs;
  std::vector<T> partial(static_cast<size_t>(nchunks), init);
  struct Ctx {
    Body* body;
    T* partial;
    Index n, cs;
  } ctx{&body, partial.data(), n, cs};
  detail::run_chunks(
      space.state(), nchunks,
      [](void* p, Index c) {
        auto& k = *static_cast<Ctx*>(p);
        const Index b = c * k.cs, e = (b + k.cs < k.n) ? b + k.cs : k.n;
        T acc = k.partial[c];
        for (Index i = b; i < e; ++i) (*k.body)(i, acc);
        k.partial[c] = acc;
      },
      &ctx);
  T result = init;
  for (Index c = 0; c < nchunks; ++c) result = join(result, partial[static_cast<size_t>(c)]);
  return result;
}

// Exclusive prefix sum: out[i] = sum_{j<i} value(j); returns the total. out may alias nothing.
template <class T, class ValueFn>
T parallel_scan(const Space& space, const char* label, Index n, ValueFn&& value, T* out) {
  if (n <= 0) return T(0);
  ScopedRegion region(space.profiler(), label);
  const Index cs = chunk_size(n, 0);
  const Index nchunks = (n + cs - 1) / cs;
  std::vector<T> sums(static_cast<size_t>(nchunks) + 1, T(0));
  struct Ctx {
    ValueFn* value;
    T* out;
    T* sums;
    Index n, cs;
  } ctx{&value, out, sums.data(), n, cs};
  // pass 1: per-chunk totals
  detail::run_chunks(
      space.state(), nchunks,
      [](void* p, Index c) {
        auto& k = *static_cast<Ctx*>(p);
        const Index b = c * k.cs, e = (b + k.cs < k.n) ? b + k.cs : k.n;
        T s(0);
        for (Index i = b; i < e; ++i) s += (*k.value)(i);
        k.sums[c + 1] = s;
      },
      &ctx);
  for (Index c = 0; c < nchunks; ++c) sums[c + 1] += sums[c];
  // pass 2: local scans with chunk offsets
  detail::run_chunks(
      space.state(), nchunks,
      [](void* p, Index c) {
        auto& k = *static_cast<Ctx*>(p);
        const Index b = c * k.cs, e = (b + k.cs < k.n) ? b + k.cs : k.n;
        T s = k.sums[c];
        for (Index i = b; i < e; ++i) {
          k.out[i] = s;
          s += (*k.value)(i);
        }
      },
      &ctx);
  return sums[static_cast<size_t>(nchunks)];
}

}  // namespace amalgam::exec
