// `amalgam bench --report DIR`: the standard cases (solvers/bench_suite) on every backend and thread
// count, with warm-up and interleaved repetitions; writes DIR/results.csv, DIR/kernels.csv,
// DIR/report.md and the plots DIR/scaling.png and DIR/breakdown.png (docs/bench_report/).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <sstream>
#include <thread>

#include "apps/commands.hpp"
#include "core/errors.hpp"
#include "core/exec/exec.hpp"
#include "core/exec/simd.hpp"
#include "core/math/types.hpp"
#include "kernels/peak_flops.hpp"
#include "solvers/bench_suite.hpp"
#include "io/plot.hpp"
#include "io/writers.hpp"

namespace amalgam::cli {

namespace {

struct Config {
  exec::Backend backend;
  int threads;
  std::string name() const {
    return std::string(exec::backend_name(backend)) + " x" + std::to_string(threads);
  }
};

struct KernelRow {
  std::string label;
  long long calls = 0;
  double ns_per_item = 0, share = 0;
};

struct Result {
  std::string case_name, method, unit;
  Config config;
  double items = 0, bytes_per_item = 0, dt = 0;
  int steps = 0;
  std::vector<double> rates;  // items per second, one per repetition
  double median = 0, min = 0, max = 0, speedup = 0, efficiency = 0;
  std::string extra;
  std::vector<KernelRow> kernels;  // by time, descending
  double spread() const { return median > 0 ? (max - min) / median : 0; }
};

double median_of(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.size() % 2 ? v[v.size() / 2] : 0.5 * (v[v.size() / 2 - 1] + v[v.size() / 2]);
}

std::string fmt(const char* f, double v) {
  char b[64];
  std::snprintf(b, sizeof b, f, v);
  return b;
}

// STREAM-style triad a = b + s c over three arrays of 2^25 floats (384 MiB), best of 5 after one
// untimed pass; bytes counted as 3 x 4 per item (no write-allocate traffic, as STREAM counts).
double triad_gb_per_s(const exec::Space& space) {
  const exec::Index n = exec::Index(1) << 25;
  std::vector<float> a(size_t(n), 0.f), b(size_t(n), 1.f), c(size_t(n), 2.f);
  double best = 0;
  for (int r = 0; r < 6; ++r) {
    const auto t0 = std::chrono::steady_clock::now();
    exec::parallel_for(space, "bench.triad", n,
                       [&](exec::Index i) { a[size_t(i)] = b[size_t(i)] + 0.5f * c[size_t(i)]; });
    const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (r > 0) best = std::max(best, 12.0 * double(n) / s / 1e9);
  }
  return best;
}

// Arithmetic peak of the kernels' code on the current SIMD path (kernels/peak_flops.cpp:
// independent multiply-add chains, multiply and add separate as the kernels compile), GFLOP/s,
// best of 5 after one untimed pass.
double peak_gflops(const exec::Space& space) {
  const int chunks = 64 * space.threads(), iters = 1 << 15;
  std::vector<Real> sink(std::size_t(chunks), Real(0));
  double best = 0;
  for (int r = 0; r < 6; ++r) {
    const auto t0 = std::chrono::steady_clock::now();
    const double flops = peak_flops_run(space, chunks, iters, sink.data());
    const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (r > 0) best = std::max(best, flops / s / 1e9);
  }
  return best;
}

// The roofline of the report's main kernels: floating-point operations and bytes from memory per
// item (particle-substep or directed bond), counted by hand from the source, float build. The
// count, line by line, and what the bytes include: docs/roofline.md. A kernel that changes must
// change its row there and here (the section says the count's commit).
struct RooflineCost {
  const char* case_name;
  const char* region;  // the profiler region (exec::parallel_for label) that times it
  double flops, bytes;
};
constexpr char kRooflineCounted[] =
    "39f9e91 (G2P recounted for its whole-row gather), and for b - I instead of F + F_lo at "
    "8dc400e (2026-11-29)";
// MPM: the particle attributes read and written (no write-allocate, as the triad counts) plus the
// dilated grid blocks amortised over a bin's ~1,450 particles; stress at one polar iteration (the
// timed window's). The report's spheres keep b - I (MpmSolver::keeps_b): P2G reads b (24 B) instead
// of F and adds its Cholesky factor (17 flops); G2P reads and writes b instead of F + F_lo (48 B
// instead of 144) and updates it in 174 flops instead of F's 135. PD (the case's plastic +
// fracture configuration, AVX2): the bond arrays streamed plus the rows' per-particle traffic; the
// neighbours' records come from cache.
const RooflineCost kRoofline[] = {
    {"mpm_mls", "mpm.p2g", 831, 92 + 42},      {"mpm_mls", "mpm.g2p", 828, 144 + 19},
    {"mpm_apic", "mpm.p2g", 1425, 92 + 42},    {"mpm_apic", "mpm.g2p", 1200, 144 + 19},
    {"mpm_flip", "mpm.p2g", 1415, 56 + 84},    {"mpm_flip", "mpm.g2p", 1462, 120 + 38},
    {"peridynamics", "pd.dilatation", 59, 26}, {"peridynamics", "pd.forces", 63, 39},
};

std::string read_first(const std::string& path, const std::string& key) {
  std::ifstream in(path);
  std::string line;
  while (std::getline(in, line))
    if (line.rfind(key, 0) == 0) {
      const auto c = line.find(':');
      std::string v = c == std::string::npos ? line : line.substr(c + 1);
      v.erase(0, v.find_first_not_of(" \t"));
      return v;
    }
  return "unknown";
}

struct Previous {
  double median = 0, spread = 0;
};

// results.csv of an earlier run, by "case|backend|threads".
std::map<std::string, Previous> read_previous(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw InputError(path + ": cannot open the previous results for --compare");
  std::stringstream ss;
  ss << in.rdbuf();
  const std::string text = ss.str();
  std::map<std::string, Previous> out;
  std::istringstream lines(text);
  std::string line;
  std::vector<std::string> head;
  int lineno = 0;
  while (std::getline(lines, line)) {
    ++lineno;
    std::vector<std::string> f(1);  // fields, quotes removed (RFC 4180)
    bool quoted = false;
    for (size_t i = 0; i < line.size(); ++i) {
      const char c = line[i];
      if (quoted && c == '"' && i + 1 < line.size() && line[i + 1] == '"')
        f.back() += '"', ++i;
      else if (c == '"')
        quoted = !quoted;
      else if (c == ',' && !quoted)
        f.emplace_back();
      else
        f.back() += c;
    }
    if (lineno == 1) {
      head = f;
      continue;
    }
    if (f.size() < head.size()) continue;
    std::map<std::string, std::string> row;
    for (size_t i = 0; i < head.size(); ++i) row[head[i]] = f[i];
    try {
      out[row.at("case") + "|" + row.at("backend") + "|" + row.at("threads")] = {
          std::stod(row.at("median")), std::stod(row.at("spread_pct")) / 100};
    } catch (const std::exception&) {
      throw InputError(path + ":" + std::to_string(lineno) +
                       ": not a results.csv row of amalgam bench --report");
    }
  }
  return out;
}

void write_file(const std::filesystem::path& p, const std::string& text) {
  write_file_atomic(p.string(), text);
}

struct ReportOptions {
  std::string dir, compare, commit = "unknown";
  double scale = 1;
  int reps = 5, warmup = 2, steps = 0;  // steps 0: per case (below)
  std::vector<int> threads = {1, 2};
  std::vector<exec::Backend> backends = exec::available_backends();
  std::vector<std::string> cases;  // empty: all
};

int default_steps(const std::string& name) {
  if (name == "mpm_implicit" || name == "peridynamics") return 4;
  return 8;
}

std::vector<Config> configs_of(const ReportOptions& o) {
  std::vector<Config> out;
  for (auto b : o.backends)
    for (int t : o.threads) {
      if (b == exec::Backend::Serial && t != 1) continue;
      const int real_t = exec::Space(b, t).threads();  // Kokkos caps at its concurrency
      if (real_t != t) continue;
      out.push_back({b, t});
    }
  return out;
}

// Runs one case on every configuration: builds each, warms each up, then times the
// repetitions interleaved (rep 0 of every configuration, then rep 1, ...) so slow drifts of a
// shared machine spread over all configurations instead of biasing one.
std::vector<Result> run_case(const BenchCase& bc, const ReportOptions& o,
                             const std::vector<Config>& configs) {
  const int steps = o.steps > 0 ? o.steps : default_steps(bc.name);
  std::vector<BenchInstance> inst;
  std::vector<exec::Profiler> prof(configs.size());
  std::vector<Result> res(configs.size());
  // Set-up (sampling, bond families, surface-correction constants) on every core: results are
  // bitwise the same on every backend, so each configuration still starts from the same state.
  const exec::Space setup(exec::Backend::OpenMP, exec::hardware_threads());
  for (size_t c = 0; c < configs.size(); ++c) {
    const exec::Space space(configs[c].backend, configs[c].threads);
    inst.push_back(bc.make(o.scale, setup));
    for (int w = 0; w < o.warmup; ++w) inst[c].step(space);
    inst[c].reset_extra();
    Result& r = res[c];
    r.case_name = bc.name, r.method = bc.method, r.unit = bc.unit, r.config = configs[c];
    r.items = inst[c].items, r.bytes_per_item = inst[c].bytes_per_item, r.dt = inst[c].dt,
    r.steps = steps;
  }
  for (int rep = 0; rep < o.reps; ++rep)
    for (size_t c = 0; c < configs.size(); ++c) {
      const exec::Space space(configs[c].backend, configs[c].threads, &prof[c]);
      const auto t0 = std::chrono::steady_clock::now();
      for (int s = 0; s < steps; ++s) inst[c].step(space);
      const double sec =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      res[c].rates.push_back(inst[c].items * steps / sec);
    }
  for (size_t c = 0; c < configs.size(); ++c) {
    Result& r = res[c];
    r.median = median_of(r.rates);
    r.min = *std::min_element(r.rates.begin(), r.rates.end());
    r.max = *std::max_element(r.rates.begin(), r.rates.end());
    r.extra = inst[c].extra();
    const double per = 1e9 / (r.items * steps * o.reps);
    const double total = prof[c].total_seconds();
    for (const auto& reg : prof[c].regions())
      r.kernels.push_back(
          {reg.label, reg.calls, reg.seconds * per, total > 0 ? reg.seconds / total : 0});
    std::sort(r.kernels.begin(), r.kernels.end(),
              [](const KernelRow& a, const KernelRow& b) { return a.ns_per_item > b.ns_per_item; });
  }
  double serial = 0;
  std::map<exec::Backend, double> one_thread;
  for (const Result& r : res) {
    if (r.config.backend == exec::Backend::Serial) serial = r.median;
    if (r.config.threads == 1) one_thread[r.config.backend] = r.median;
  }
  for (Result& r : res) {
    r.speedup = serial > 0 ? r.median / serial : 0;
    const double base = one_thread.count(r.config.backend) ? one_thread[r.config.backend] : 0;
    r.efficiency = base > 0 ? r.median / (base * r.config.threads) : 0;
  }
  return res;
}

// RFC 4180: a field with a comma, quote or newline is quoted, its quotes doubled.
std::string csv_field(const std::string& f) {
  if (f.find_first_of(",\"\n") == std::string::npos) return f;
  std::string q = "\"";
  for (char c : f) q += c == '"' ? std::string("\"\"") : std::string(1, c);
  return q + "\"";
}

// Numeric columns first, free text (method, extra) last and quoted.
std::string results_csv(const std::vector<Result>& all) {
  std::string s =
      "case,backend,threads,unit,items,steps,reps,median,min,max,spread_pct,speedup_vs_serial,"
      "parallel_efficiency,ns_per_item,bytes_per_item,dt,method,extra\n";
  for (const Result& r : all) {
    s += r.case_name + "," + exec::backend_name(r.config.backend) + "," +
         std::to_string(r.config.threads) + "," + r.unit + "," + fmt("%.0f", r.items) + "," +
         std::to_string(r.steps) + "," + std::to_string(r.rates.size()) + "," +
         fmt("%.6g", r.median) + "," + fmt("%.6g", r.min) + "," + fmt("%.6g", r.max) + "," +
         fmt("%.2f", 100 * r.spread()) + "," + fmt("%.4f", r.speedup) + "," +
         fmt("%.4f", r.efficiency) + "," + fmt("%.3f", 1e9 / r.median) + "," +
         fmt("%.1f", r.bytes_per_item) + "," + fmt("%.3g", r.dt) + "," + csv_field(r.method) + "," +
         csv_field(r.extra) + "\n";
  }
  return s;
}

std::string kernels_csv(const std::vector<Result>& all) {
  std::string s = "case,backend,threads,label,calls,ns_per_item,share_pct\n";
  for (const Result& r : all)
    for (const KernelRow& k : r.kernels)
      s += r.case_name + "," + exec::backend_name(r.config.backend) + "," +
           std::to_string(r.config.threads) + "," + k.label + "," + std::to_string(k.calls) + "," +
           fmt("%.4g", k.ns_per_item) + "," + fmt("%.2f", 100 * k.share) + "\n";
  return s;
}

std::string rate(double v) {
  return fmt("%.3g", v);
}

// A case's Serial result and its fastest 2-thread one (either may be null).
std::pair<const Result*, const Result*> serial_and_best2(const std::vector<Result>& all,
                                                         const std::string& name) {
  const Result* serial = nullptr;
  const Result* best2 = nullptr;
  for (const Result& r : all) {
    if (r.case_name != name) continue;
    if (r.config.backend == exec::Backend::Serial) serial = &r;
    if (r.config.threads == 2 && (!best2 || r.median > best2->median)) best2 = &r;
  }
  return {serial, best2};
}

// The kernels of a result that make up at least 90 % of its profiled time (at most 8), the rest
// summed as "other".
std::vector<KernelRow> top_kernels(const Result& r) {
  std::vector<KernelRow> out;
  double share = 0;
  KernelRow other{"other", 0, 0, 0};
  for (const KernelRow& k : r.kernels) {
    if (share < 0.9 && out.size() < 8) {
      out.push_back(k);
      share += k.share;
    } else {
      other.ns_per_item += k.ns_per_item, other.share += k.share, other.calls += k.calls;
    }
  }
  if (other.share > 0) out.push_back(other);
  return out;
}

// The roofline section: the ceilings of each thread count, and each counted kernel's floor (the
// larger of its bytes at the triad bandwidth and its flops at the arithmetic peak: the physical
// limit of that kernel on this machine) against its profiler region's time, Serial and the
// fastest 2-thread configuration.
std::string roofline_md(const std::vector<Result>& all, const std::map<int, double>& bandwidth,
                        const std::map<int, double>& peak) {
  std::ostringstream md;
  md << "## Roofline: each kernel against this machine's ceilings\n\n"
     << "Ceilings measured in this run: memory bandwidth (the STREAM triad above) and arithmetic "
        "peak (`kernels/peak_flops.cpp`: independent multiply-add chains on the vectors of the "
        "SIMD path above, a multiply and an add as the kernels are compiled, without FMA "
        "contraction); the ridge point is where a kernel's flops per byte make the two take the "
        "same time.\n\n| threads | bandwidth | arithmetic peak | ridge point |\n|---:|---:|---:|---:|\n";
  for (const auto& [t, gb] : bandwidth) {
    const auto p = peak.find(t);
    const double gf = p != peak.end() ? p->second : 0;
    md << "| " << t << " | " << fmt("%.1f", gb) << " GB/s | " << fmt("%.1f", gf) << " GFLOP/s | "
       << fmt("%.1f", gb > 0 ? gf / gb : 0) << " flop/B |\n";
  }
  md << "\nPer kernel: flops and bytes moved per item (particle-substep or directed bond) counted "
        "by hand from the source at "
     << kRooflineCounted
     << " (float; docs/roofline.md has the count line by line; +-10 % on flops, +-30 % on the "
        "grid's share of the bytes). *floor*: the larger of bytes / bandwidth and flops / peak, the physical limit "
        "of the kernel on this machine at that thread count; *bound*: which of the two it is; "
        "*measured*: the kernel's profiler region, ns per item; *x floor*: measured / floor.\n\n"
     << "| case | kernel | flops/item | bytes/item | flop/B | bound | floor, 1 thread | serial x1 "
        "| x floor | floor, 2 threads | fastest x2 | x floor |\n"
     << "|---|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|\n";
  const auto floor_ns = [&](const RooflineCost& k, int t) {
    const auto b = bandwidth.find(t);
    const auto p = peak.find(t);
    const double mem = b != bandwidth.end() && b->second > 0 ? k.bytes / b->second : 0;
    const double fl = p != peak.end() && p->second > 0 ? k.flops / p->second : 0;
    return std::pair<double, bool>(std::max(mem, fl), fl > mem);
  };
  for (const RooflineCost& k : kRoofline) {
    const auto [serial, best2] = serial_and_best2(all, k.case_name);
    if (!serial && !best2) continue;
    const auto measured = [&](const Result* r) {
      if (r)
        for (const KernelRow& row : r->kernels)
          if (row.label == k.region) return row.ns_per_item;
      return 0.0;
    };
    const auto [f1, compute1] = floor_ns(k, 1);
    const auto [f2, compute2] = floor_ns(k, 2);
    const double m1 = measured(serial), m2 = measured(best2);
    const auto cell = [](double v, const char* f) { return v > 0 ? fmt(f, v) : std::string("-"); };
    md << "| " << k.case_name << " | " << k.region << " | " << fmt("%.0f", k.flops) << " | "
       << fmt("%.0f", k.bytes) << " | " << fmt("%.1f", k.flops / k.bytes) << " | "
       << (compute2 || (f2 == 0 && compute1) ? "compute" : "memory") << " | " << cell(f1, "%.1f")
       << " | " << cell(m1, "%.1f") << " | " << cell(f1 > 0 && m1 > 0 ? m1 / f1 : 0, "%.1f")
       << " | " << cell(f2, "%.1f") << " | " << cell(m2, "%.1f") << " ("
       << (best2 ? best2->config.name() : std::string("-")) << ") | "
       << cell(f2 > 0 && m2 > 0 ? m2 / f2 : 0, "%.1f") << " |\n";
  }
  md << "\n";
  return md.str();
}

std::string report_md(const std::vector<Result>& all, const std::vector<BenchCase>& cases,
                      const ReportOptions& o, const std::vector<Config>& configs,
                      const std::map<int, double>& bandwidth, const std::map<int, double>& peak,
                      const std::map<std::string, Previous>* prev, double wall_seconds) {
  std::ostringstream md;
  std::time_t now = std::time(nullptr);
  char date[32];
  std::strftime(date, sizeof date, "%Y-%m-%d %H:%M UTC", std::gmtime(&now));
  md << "# Amalgam benchmark report\n\n"
     << "Generated by `scripts/bench_report.sh` (which runs `amalgam bench --report DIR/previous`, then "
        "`amalgam bench --report DIR --compare DIR/previous/results.csv`; see docs/benchmarks.md). Data: "
        "[results.csv](results.csv) (one row per case and configuration), [kernels.csv](kernels.csv) "
        "(profiler regions).\n\n"
     << "| | |\n|---|---|\n"
     << "| date | " << date << " |\n"
     << "| commit | " << o.commit << " |\n"
     << "| CPU | " << read_first("/proc/cpuinfo", "model name") << " |\n"
     << "| hardware threads | " << exec::hardware_threads() << " |\n"
     << "| memory | "
     << fmt("%.1f", std::atof(read_first("/proc/meminfo", "MemTotal").c_str()) / 1048576.0)
     << " GiB |\n"
     << "| precision | " << real_name() << " |\n"
     << "| SIMD path | " << exec::simd_description() << " |\n"
     << "| compiler | g++ " << __VERSION__ << ", Release"
     << " |\n"
     << "| backends | ";
  for (const Config& c : configs) md << c.name() << "; ";
  md << (exec::backend_compiled(exec::Backend::Kokkos) ? exec::kokkos_version()
                                                       : std::string("(no Kokkos)"))
     << " |\n"
     << "| STREAM triad | ";
  for (const auto& [t, gb] : bandwidth)
    md << t << " thread" << (t > 1 ? "s" : "") << ": " << fmt("%.1f", gb) << " GB/s; ";
  md << " |\n| arithmetic peak | ";
  for (const auto& [t, gf] : peak)
    md << t << " thread" << (t > 1 ? "s" : "") << ": " << fmt("%.1f", gf) << " GFLOP/s; ";
  md << " |\n| wall time | " << fmt("%.0f", wall_seconds) << " s |\n\n";
  md << "**Method.** Each case is built once per configuration (same seed, same state), stepped "
     << o.warmup << " times untimed, then timed in " << o.reps
     << " repetitions of a fixed number of steps. Repetitions are interleaved across configurations "
        "(repetition 1 of every configuration, then repetition 2, ...), so a slow drift of this shared "
        "machine spreads over all of them. Throughput is the **median** over repetitions with "
        "[min, max]; **spread** = (max - min) / median is the run's own noise figure. Speed-up is "
        "against Serial; parallel efficiency = throughput / (threads x the same backend's 1-thread "
        "throughput). ns/item = 1e9 / median. Bytes per item: resident solver state (particle "
        "attributes + sort scratch + grid leaves, per particle; or bond arrays + particles, per "
        "directed bond). Items: particles per substep, or directed bonds per step "
        "(bond-updates: dilatation + force passes of a whole step).\n\n";

  md << "## Summary: throughput per configuration (median, and the spread in brackets)\n\n| case | unit |";
  for (const Config& c : configs) md << " " << c.name() << " |";
  md << "\n|---|---|";
  for (size_t i = 0; i < configs.size(); ++i) md << "---:|";
  md << "\n";
  for (const BenchCase& bc : cases) {
    md << "| " << bc.name << " | " << bc.unit << " |";
    for (const Config& c : configs)
      for (const Result& r : all)
        if (r.case_name == bc.name && r.config.backend == c.backend &&
            r.config.threads == c.threads)
          md << " " << rate(r.median) << " (" << fmt("%.0f", 100 * r.spread()) << " %) |";
    md << "\n";
  }
  md << "\n![speed-up against Serial per case and configuration](scaling.png)\n\n"
     << "![where the time goes: profiler regions per case, Serial and the fastest 2-thread configuration]"
        "(breakdown.png)\n\n";

  for (const BenchCase& bc : cases) {
    md << "## " << bc.name << ": " << bc.method << "\n\n"
       << bc.scene << ".\n\n"
       << "| configuration | " << bc.unit
       << " | spread | ns/item | speed-up | efficiency | bytes/item | "
       << "floor ns/item | notes |\n|---|---:|---:|---:|---:|---:|---:|---:|---|\n";
    const auto [serial, best2] = serial_and_best2(all, bc.name);
    for (const Result& r : all) {
      if (r.case_name != bc.name) continue;
      const auto bw = bandwidth.find(r.config.threads);
      const double floor =
          bw != bandwidth.end() && bw->second > 0 ? r.bytes_per_item / bw->second : 0;
      md << "| " << r.config.name() << " | " << rate(r.median) << " [" << rate(r.min) << ", "
         << rate(r.max) << "] | " << fmt("%.1f", 100 * r.spread()) << " % | "
         << fmt("%.1f", 1e9 / r.median) << " | " << fmt("%.2f", r.speedup) << " | "
         << fmt("%.2f", r.efficiency) << " | " << fmt("%.0f", r.bytes_per_item) << " | "
         << fmt("%.2f", floor) << " | " << r.extra << " |\n";
    }
    md << "\n*floor ns/item*: the resident bytes per item streamed once at the STREAM triad bandwidth of "
          "that thread count, a lower bound a step cannot beat if it touches all its state once.\n\n";
    for (const Result* r : {serial, best2}) {
      if (!r) continue;
      md << "Kernels, " << r->config.name()
         << " (ns per item per step, share of profiled time):\n\n"
         << "| region | ns/item | share | calls |\n|---|---:|---:|---:|\n";
      for (const KernelRow& k : top_kernels(*r))
        md << "| " << k.label << " | " << fmt("%.2f", k.ns_per_item) << " | "
           << fmt("%.1f", 100 * k.share) << " % | " << k.calls << " |\n";
      md << "\n";
      if (r == best2 && serial == best2) break;
    }
  }

  md << roofline_md(all, bandwidth, peak);

  if (prev) {
    int within = 0, total = 0;
    std::ostringstream rows;
    for (const Result& r : all) {
      const auto it = prev->find(r.case_name + "|" + exec::backend_name(r.config.backend) + "|" +
                                 std::to_string(r.config.threads));
      if (it == prev->end()) continue;
      const double change = r.median / it->second.median - 1;
      const double noise = std::max(r.spread(), it->second.spread);
      const bool ok = std::abs(change) <= noise;
      within += ok, ++total;
      rows << "| " << r.case_name << " | " << r.config.name() << " | " << rate(it->second.median)
           << " | " << rate(r.median) << " | " << fmt("%+.1f", 100 * change) << " % | "
           << fmt("%.1f", 100 * noise) << " % | " << (ok ? "yes" : "**no**") << " |\n";
    }
    md << "## Repeatability: this run against the previous one\n\n"
       << "Medians of two consecutive runs of the whole report on the same build; *noise* is the "
          "larger of the two runs' spreads (max - min over the repetitions, relative to the median). "
       << within << " of " << total
       << " configurations changed by no more than the noise the runs state.\n\n"
       << "| case | configuration | previous | this run | change | noise | within |\n"
       << "|---|---|---:|---:|---:|---:|---|\n"
       << rows.str() << "\n";
  }
  // Tables the report script made before this run (bench/microbench_table.py, bench/pd_peer.py).
  for (const auto& [file, title] :
       {std::pair<const char*, const char*>{
            "microbench.md",
            "Microbenchmarks: every solver's hot kernels per backend "
            "(bench/microbench_table.py)"},
        {"peer_lammps.md", "Peer: LAMMPS peri/lps (bench/pd_peer.py)"}}) {
    std::ifstream in(std::filesystem::path(o.dir) / file);
    if (!in) continue;
    std::stringstream ss;
    ss << in.rdbuf();
    md << "## " << title << "\n\n" << ss.str() << "\n";
  }
  return md.str();
}

Image scaling_plot(const std::vector<Result>& all, const std::vector<BenchCase>& cases,
                   const std::vector<Config>& configs) {
  BarChart chart;
  chart.title = "SPEED-UP AGAINST SERIAL (MEDIAN, BARS: MIN-MAX)";
  chart.ylabel = "x serial";
  chart.reference = 1.0;
  for (const Config& c : configs) chart.series.push_back(c.name());
  for (const BenchCase& bc : cases) {
    chart.groups.push_back(bc.name);
    std::vector<double> v, lo, hi;
    double serial = 0;
    for (const Result& r : all)
      if (r.case_name == bc.name && r.config.backend == exec::Backend::Serial) serial = r.median;
    for (const Config& c : configs)
      for (const Result& r : all)
        if (r.case_name == bc.name && r.config.backend == c.backend &&
            r.config.threads == c.threads) {
          v.push_back(serial > 0 ? r.median / serial : 0);
          lo.push_back(serial > 0 ? r.min / serial : 0);
          hi.push_back(serial > 0 ? r.max / serial : 0);
        }
    chart.values.push_back(v), chart.low.push_back(lo), chart.high.push_back(hi);
  }
  return plot_bars(chart);
}

Image breakdown_plot(const std::vector<Result>& all, const std::vector<BenchCase>& cases) {
  std::vector<BreakdownBar> bars;
  for (const BenchCase& bc : cases) {
    const auto [serial, best2] = serial_and_best2(all, bc.name);
    for (const Result* r : {serial, best2}) {
      if (!r) continue;
      BreakdownBar b;
      b.label = bc.name + " " + r->config.name() + " " + fmt("%.0f", 1e9 / r->median) + " NS/ITEM";
      for (const KernelRow& k : top_kernels(*r)) b.segments.push_back({k.label, k.ns_per_item});
      bars.push_back(b);
    }
  }
  return plot_breakdown("TIME PER ITEM BY PROFILER REGION (NS)", bars);
}

}  // namespace

int bench_report(const Options& opts) {
  ReportOptions o;
  o.dir = *opts.get("--report");
  if (auto* v = opts.get("--compare")) o.compare = *v;
  if (auto* v = opts.get("--commit")) o.commit = *v;
  if (auto* v = opts.get("--scale")) o.scale = parse_double("--scale", *v, 1e-3, 64);
  if (auto* v = opts.get("--reps")) o.reps = parse_int("--reps", *v, 1, 1000);
  if (auto* v = opts.get("--steps")) o.steps = parse_int("--steps", *v, 1, 100000);
  if (auto* v = opts.get("--warmup")) o.warmup = parse_int("--warmup", *v, 0, 1000);
  if (auto* v = opts.get("--threads")) {
    o.threads.clear();
    std::stringstream ss(*v);
    std::string t;
    while (std::getline(ss, t, ',')) o.threads.push_back(parse_int("--threads", t, 1, 4096));
  }
  if (auto* v = opts.get("--backends")) {
    o.backends.clear();
    std::stringstream ss(*v);
    std::string b;
    while (std::getline(ss, b, ',')) o.backends.push_back(exec::parse_backend(b));
  }
  std::vector<BenchCase> cases;
  const std::vector<BenchCase> all_cases = standard_bench_cases();
  if (auto* v = opts.get("--cases")) {
    std::stringstream ss(*v);
    std::string name;
    while (std::getline(ss, name, ',')) {
      auto it = std::find_if(all_cases.begin(), all_cases.end(),
                             [&](const BenchCase& c) { return c.name == name; });
      if (it == all_cases.end()) {
        std::string known;
        for (const auto& c : all_cases) known += (known.empty() ? "" : ", ") + c.name;
        throw std::invalid_argument("--cases: unknown case '" + name + "' (known: " + known + ")");
      }
      cases.push_back(*it);
    }
  } else {
    cases = all_cases;
  }
  std::map<std::string, Previous> prev;
  if (!o.compare.empty()) prev = read_previous(o.compare);  // fail before the long run
  std::filesystem::create_directories(o.dir);
  const std::vector<Config> configs = configs_of(o);
  const auto t0 = std::chrono::steady_clock::now();

  // The roofline's ceilings per thread count: the triad's bandwidth and the arithmetic peak.
  std::map<int, double> bandwidth, peak;
  for (int t : o.threads) {
    const exec::Space space(t == 1 ? exec::Backend::Serial : exec::Backend::OpenMP, t);
    if (space.threads() == t) {
      bandwidth[t] = triad_gb_per_s(space);
      peak[t] = peak_gflops(space);
    }
    std::cout << "bench report: STREAM triad, " << t << " thread(s): " << fmt("%.1f", bandwidth[t])
              << " GB/s; arithmetic peak (" << exec::simd_path_name(exec::simd_path())
              << "): " << fmt("%.1f", peak[t]) << " GFLOP/s" << std::endl;
  }
  std::vector<Result> all;
  for (const BenchCase& bc : cases) {
    const auto c0 = std::chrono::steady_clock::now();
    for (Result& r : run_case(bc, o, configs)) {
      std::cout << "case=" << r.case_name << " backend=" << exec::backend_name(r.config.backend)
                << " threads=" << r.config.threads << " median=" << rate(r.median)
                << " min=" << rate(r.min) << " max=" << rate(r.max) << " unit=" << r.unit
                << " spread=" << fmt("%.1f", 100 * r.spread()) << "%"
                << (r.extra.empty() ? "" : " ") << r.extra << std::endl;
      all.push_back(std::move(r));
    }
    std::cout << "  (" << bc.name << ": "
              << fmt("%.0f",
                     std::chrono::duration<double>(std::chrono::steady_clock::now() - c0).count())
              << " s)" << std::endl;
  }
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const std::filesystem::path dir(o.dir);
  write_file(dir / "results.csv", results_csv(all));
  write_file(dir / "kernels.csv", kernels_csv(all));
  write_png((dir / "scaling.png").string(), scaling_plot(all, cases, configs));
  write_png((dir / "breakdown.png").string(), breakdown_plot(all, cases));
  write_file(dir / "report.md", report_md(all, cases, o, configs, bandwidth, peak,
                                          prev.empty() ? nullptr : &prev, wall));
  std::cout << "bench report: " << (dir / "report.md").string() << " (" << fmt("%.0f", wall)
            << " s)" << std::endl;
  return kOk;
}

}  // namespace amalgam::cli
