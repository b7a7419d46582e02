// exec layer: parallel_for / parallel_reduce / parallel_scan are correct and bitwise identical on
// every backend and thread count; the profiler records labelled regions.
#include <gtest/gtest.h>

#include <cstdio>
#include <fstream>

#include "core/memory/huge_pages.hpp"

#include <cmath>
#include <numeric>

#include <tbb/parallel_for.h>

#include <atomic>
#include <chrono>

#include "test_util.hpp"
#include "thread_recorder.hpp"

using namespace amalgam;

TEST(Exec, ParallelForVisitsEveryIndexOnce) {
  for (const auto& c : test::all_configs()) {
    exec::Space s(c.backend, c.threads);
    for (exec::Index n : {0, 1, 7, 1000, 100003}) {
      std::vector<int> hits(static_cast<size_t>(n), 0);
      exec::parallel_for(s, "t.for", n, [&](exec::Index i) { hits[size_t(i)] += 1; });
      for (auto h : hits) ASSERT_EQ(h, 1) << c.name() << " n=" << n;
    }
  }
}

TEST(Exec, ReduceIsBitwiseIdenticalAcrossBackends) {
  // A float sum whose value depends on the combine order: it must not depend on the backend.
  const exec::Index n = 200001;
  std::vector<float> x(static_cast<size_t>(n));
  for (exec::Index i = 0; i < n; ++i)
    x[size_t(i)] = float(std::sin(double(i)) * 1e3 + 1.0 / (1.0 + double(i)));
  float ref = 0;
  bool first = true;
  for (const auto& c : test::all_configs()) {
    exec::Space s(c.backend, c.threads);
    const float r = exec::parallel_reduce(
        s, "t.reduce", n, 0.0f, [&](exec::Index i, float& acc) { acc += x[size_t(i)]; },
        [](float a, float b) { return a + b; });
    if (first) ref = r, first = false;
    EXPECT_EQ(std::memcmp(&r, &ref, sizeof r), 0) << c.name();
  }
  double exact = 0;
  for (float v : x) exact += double(v);
  EXPECT_NEAR(double(ref), exact, 1e-3 * std::abs(exact) + 1.0);
}

TEST(Exec, ScanMatchesSerialPrefixSum) {
  for (const auto& c : test::all_configs()) {
    exec::Space s(c.backend, c.threads);
    for (exec::Index n : {1, 5, 4096, 99999}) {
      std::vector<long long> out(static_cast<size_t>(n));
      const long long total = exec::parallel_scan<long long>(
          s, "t.scan", n, [](exec::Index i) { return (long long)(i % 7); }, out.data());
      long long run = 0;
      for (exec::Index i = 0; i < n; ++i) {
        ASSERT_EQ(out[size_t(i)], run) << c.name() << " i=" << i;
        run += i % 7;
      }
      EXPECT_EQ(total, run);
    }
  }
}

TEST(Exec, ProfilerTimesLabelledRegions) {
  exec::Profiler prof;
  exec::Space s(test::parallel_backend(), 2, &prof);
  std::vector<double> v(100000);
  for (int r = 0; r < 3; ++r)
    exec::parallel_for(s, "t.work", exec::Index(v.size()),
                       [&](exec::Index i) { v[size_t(i)] = std::sqrt(double(i)); });
  ASSERT_EQ(prof.regions().size(), 1u);
  EXPECT_EQ(prof.regions()[0].label, "t.work");
  EXPECT_EQ(prof.regions()[0].calls, 3);
  EXPECT_GT(prof.seconds("t.work"), 0.0);
  EXPECT_NE(prof.report().find("t.work"), std::string::npos);
}

TEST(Exec, ParseBackendRejectsUnknownNames) {
  EXPECT_EQ(exec::parse_backend("TBB"), exec::Backend::TBB);
  EXPECT_EQ(exec::parse_backend("openmp"), exec::Backend::OpenMP);
  EXPECT_THROW(exec::parse_backend("cuda"), std::invalid_argument);
  EXPECT_THROW(exec::Space(exec::Backend::OpenMP, 0), std::invalid_argument);
  if (exec::backend_compiled(exec::Backend::Kokkos)) {
    EXPECT_EQ(exec::parse_backend("Kokkos"), exec::Backend::Kokkos);
    EXPECT_EQ(exec::available_backends().back(), exec::Backend::Kokkos);
    EXPECT_NE(exec::kokkos_version().find("Kokkos "), std::string::npos);
  } else {
    EXPECT_THROW(exec::parse_backend("kokkos"), std::invalid_argument);
    EXPECT_THROW(exec::Space(exec::Backend::Kokkos, 1), std::invalid_argument);
  }
}

// with_thread_limit bounds library code built on TBB (OpenVDB's tools) to the space's threads: no
// TBB worker joins under one thread, at most one (the caller being the other) under two. Without
// the arena, TBB's default arena on a 2-core machine takes a worker for this much work.
TEST(Exec, ThreadLimitBoundsLibraryThreads) {
  for (const int threads : {1, 2}) {
    for (const exec::Backend b :
         {exec::Backend::Serial, exec::Backend::OpenMP, exec::Backend::TBB}) {
      const exec::Space space(b, threads);
      test::WorkerRecorder rec;
      std::atomic<long> sum{0};
      exec::with_thread_limit(space, [&] {
        tbb::parallel_for(0, 2000, [&](int i) {
          const auto until = std::chrono::steady_clock::now() + std::chrono::microseconds(20);
          while (std::chrono::steady_clock::now() < until) {
          }
          sum += i;
        });
      });
      EXPECT_EQ(sum.load(), 1999L * 2000 / 2);
      EXPECT_LE(rec.workers(), std::size_t(space.threads() - 1))
          << exec::backend_name(b) << " x" << threads;
    }
  }
}

// The particle set's and the grid's large arrays ask for transparent huge pages
// (core/memory/huge_pages.hpp): the 2 MiB pages inside an allocation of at least 4 MiB carry the
// kernel's "hg" advice flag (/proc/self/smaps VmFlags), and a plain std::vector's do not; the
// values are those written, and a small allocation is left alone.
namespace {
// The VmFlags of the mapping that holds address a, or "" when smaps cannot be read.
std::string vm_flags_at(std::uintptr_t a) {
  std::ifstream in("/proc/self/smaps");
  std::string line;
  bool inside = false;
  while (std::getline(in, line)) {
    unsigned long lo = 0, hi = 0;
    if (std::sscanf(line.c_str(), "%lx-%lx ", &lo, &hi) == 2 && line.find('-') < 17) {
      inside = a >= lo && a < hi;
      continue;
    }
    if (inside && line.rfind("VmFlags:", 0) == 0) return line;
  }
  return "";
}
std::uintptr_t first_huge_page(const void* p) {
  constexpr std::uintptr_t kHuge = std::uintptr_t(1) << 21;
  return (reinterpret_cast<std::uintptr_t>(p) + kHuge - 1) & ~(kHuge - 1);
}
}  // namespace

TEST(HugePages, LargeArraysAskForThemAndKeepTheirValues) {
  amalgam::HugePageVector<std::uint32_t> big(std::size_t(3) << 20);  // 12 MiB
  std::vector<std::uint32_t> plain(std::size_t(3) << 20);
  std::iota(big.begin(), big.end(), 7u);
  for (std::size_t i = 0; i < big.size(); i += 4099) ASSERT_EQ(big[i], std::uint32_t(7 + i));
  amalgam::HugePageVector<std::uint32_t> small(1000, 5u);  // below the threshold: no advice
  EXPECT_EQ(small[999], 5u);
#if defined(__linux__)
  if (!std::ifstream("/sys/kernel/mm/transparent_hugepage/enabled"))
    GTEST_SKIP() << "this kernel has no transparent huge pages";
  const std::string flags = vm_flags_at(first_huge_page(big.data()));
  if (flags.empty()) GTEST_SKIP() << "/proc/self/smaps not readable";
  EXPECT_NE(flags.find(" hg"), std::string::npos) << flags;
  EXPECT_EQ(vm_flags_at(first_huge_page(plain.data())).find(" hg"), std::string::npos);
#endif
}
