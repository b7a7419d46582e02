// Shared by the distributed gtests run under mpirun (test_dist_mpm.cpp, test_dist_pd.cpp).
#pragma once

#include <gtest/gtest.h>

#include <cstdio>
#include <cstring>

#include "core/dist/comm.hpp"
#include "core/particles/particle_set.hpp"

namespace amalgam::test {

// Collective result check: `all` (particles gathered on rank 0) is bitwise `ref`, attribute by
// attribute; the other ranks hold none.
inline void expect_gathered_bitwise(const ParticleSet& all, const ParticleSet& ref) {
  if (!dist::Comm::world().root()) {
    EXPECT_EQ(all.size(), 0u);
    return;
  }
  ASSERT_EQ(all.size(), ref.size());
  for (int a = 0; a < ref.attribute_count(); ++a) {
    const std::size_t w = std::size_t(ref.words_per_particle(a));
    EXPECT_EQ(std::memcmp(all.words(a), ref.words(a), ref.size() * w * 4), 0) << ref.name(a);
  }
}

// Non-root ranks print their failures only, with the rank.
class RankFailurePrinter : public ::testing::EmptyTestEventListener {
  void OnTestPartResult(const ::testing::TestPartResult& r) override {
    if (r.failed())
      std::fprintf(stderr, "rank %d: %s:%d: %s\n", dist::Comm::world().rank(),
                   r.file_name() ? r.file_name() : "?", r.line_number(), r.summary());
  }
};

// The main of a distributed gtest: MPI for the process's lifetime, failures of the non-root
// ranks printed with their rank, and the job fails when any rank's tests fail.
inline int run_tests_on_every_rank(int argc, char** argv) {
  dist::Session session(&argc, &argv);
  ::testing::InitGoogleTest(&argc, argv);
  if (!dist::Comm::world().root()) {
    auto& listeners = ::testing::UnitTest::GetInstance()->listeners();
    delete listeners.Release(listeners.default_result_printer());
    listeners.Append(new RankFailurePrinter);
  }
  const int rc = RUN_ALL_TESTS();
  return dist::Comm::world().max(std::int64_t(rc)) != 0 ? 1 : 0;
}

}  // namespace amalgam::test
