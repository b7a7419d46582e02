// Subcommands of the amalgam CLI. Each returns the process exit code (see README, "Exit codes").
#pragma once

#include <csignal>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"

namespace amalgam::cli {

enum ExitCode { kOk = 0, kSimulationFailed = 1, kUsage = 2, kBadInput = 3 };

int run_command(const std::vector<std::string>& args);
int validate_command(const std::vector<std::string>& args);
int info_command(const std::vector<std::string>& args);
int bench_command(const std::vector<std::string>& args);
int plot_command(const std::vector<std::string>& args);
int surface_command(const std::vector<std::string>& args);
int merge_command(const std::vector<std::string>& args);

// Shared option parsing: "--key value" pairs and flags; throws std::invalid_argument.
struct Options {
  std::vector<std::string> positional;
  std::vector<std::pair<std::string, std::string>> values;
  std::vector<std::string> flags;
  const std::string* get(const std::string& key) const;
  bool flag(const std::string& key) const;
};
Options parse_options(const std::vector<std::string>& args,
                      const std::vector<std::string>& value_keys,
                      const std::vector<std::string>& flag_keys);
// `amalgam bench --report DIR ...` (apps/bench_report.cpp). Throws std::invalid_argument on a
// bad option, InputError on an unreadable --compare file.
int bench_report(const Options& o);
// A message for the terminal: control characters from input files or names (escape sequences,
// NUL, newlines) shown as \xNN instead of being sent raw.
std::string printable(const std::string& s);
// What the process is doing, for the top-level error handler of main(): "reading scene file X",
// "setting up X", "frame 12 of X".
void set_phase(const std::string& phase);
const std::string& current_phase();
// Seconds since this process was started (exec), from /proc/self/stat and CLOCK_BOOTTIME
// (Linux; the start is known to a clock tick, 10 ms): what `amalgam run`'s set-up summary counts
// from. -1 where unknown.
double process_age_seconds();
// CPU seconds of this process so far, all its threads (CLOCK_PROCESS_CPUTIME_ID).
double process_cpu_seconds();
// process_age_seconds() when main() began: the dynamic loading and static initialisation.
extern double g_age_at_main;
int parse_int(const std::string& key, const std::string& value, int lo, int hi);
double parse_double(const std::string& key, const std::string& value, double lo, double hi);

}  // namespace amalgam::cli

namespace amalgam {
struct Scene;
}

namespace amalgam::cli {

// Set by the SIGINT/SIGTERM handler of `amalgam run` (0 until a signal arrives).
extern volatile std::sig_atomic_t g_signal;
extern "C" void on_signal(int sig);
std::string format_seconds(double s);
// Rows of an existing diagnostics.csv for frames before `first_frame` (kept on resume).
std::vector<std::string> earlier_rows(const std::string& csv, int first_frame);

}  // namespace amalgam::cli
