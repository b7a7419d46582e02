#include "core/exec/profiler.hpp"

#include <algorithm>
#include <cstdio>
#include <cstring>

namespace amalgam::exec {

void Profiler::add(const char* label, double seconds) {
  // Few distinct labels (tens): a linear scan per region call is cheaper than hashing.
  for (auto& r : regions_) {
    if (r.label == label) {
      r.seconds += seconds;
      ++r.calls;
      return;
    }
  }
  regions_.push_back({label, seconds, 1});
}

double Profiler::total_seconds() const {
  double s = 0;
  for (const auto& r : regions_) s += r.seconds;
  return s;
}

double Profiler::seconds(const std::string& label) const {
  for (const auto& r : regions_)
    if (r.label == label) return r.seconds;
  return 0.0;
}

std::string Profiler::report(double wall_seconds) const {
  std::vector<RegionStats> sorted = regions_;
  std::sort(sorted.begin(), sorted.end(),
            [](const RegionStats& a, const RegionStats& b) { return a.seconds > b.seconds; });
  const double denom = wall_seconds > 0 ? wall_seconds : total_seconds();
  std::string out;
  char line[256];
  std::snprintf(line, sizeof line, "  %-28s %10s %8s %10s %7s\n", "kernel", "total[s]", "calls",
                "mean[ms]", "share");
  out += line;
  for (const auto& r : sorted) {
    std::snprintf(line, sizeof line, "  %-28s %10.3f %8lld %10.3f %6.1f%%\n", r.label.c_str(),
                  r.seconds, r.calls, r.calls ? 1e3 * r.seconds / double(r.calls) : 0.0,
                  denom > 0 ? 100.0 * r.seconds / denom : 0.0);
    out += line;
  }
  return out;
}

}  // namespace amalgam::exec
