// Profiler: accumulates wall time and call counts per labelled region (one entry per label).
// Regions are timed at the granularity of a parallel_for call, never per item.
#pragma once

#include <chrono>
#include <string>
#include <vector>

namespace amalgam::exec {

struct RegionStats {
  std::string label;
  double seconds = 0.0;
  long long calls = 0;
};

class Profiler {
 public:
  void add(const char* label, double seconds);
  const std::vector<RegionStats>& regions() const { return regions_; }
  double total_seconds() const;
  double seconds(const std::string& label) const;
  void reset() { regions_.clear(); }
  // Table sorted by time, with percentages of `wall_seconds` (or of the sum when <= 0).
  std::string report(double wall_seconds = 0.0) const;

 private:
  std::vector<RegionStats> regions_;
};

class ScopedRegion {
 public:
  ScopedRegion(Profiler* p, const char* label) : p_(p), label_(label) {
    if (p_) t0_ = std::chrono::steady_clock::now();
  }
  ~ScopedRegion() {
    if (p_) {
      const auto t1 = std::chrono::steady_clock::now();
      p_->add(label_, std::chrono::duration<double>(t1 - t0_).count());
    }
  }
  ScopedRegion(const ScopedRegion&) = delete;
  ScopedRegion& operator=(const ScopedRegion&) = delete;

 private:
  Profiler* p_;
  const char* label_;
  std::chrono::steady_clock::time_point t0_;
};

}  // namespace amalgam::exec
