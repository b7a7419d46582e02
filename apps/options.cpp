#include <time.h>
#include <unistd.h>

#include <cstdio>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include "apps/commands.hpp"

namespace amalgam::cli {

const std::string* Options::get(const std::string& key) const {
  for (const auto& kv : values)
    if (kv.first == key) return &kv.second;
  return nullptr;
}

bool Options::flag(const std::string& key) const {
  for (const auto& f : flags)
    if (f == key) return true;
  return false;
}

Options parse_options(const std::vector<std::string>& args,
                      const std::vector<std::string>& value_keys,
                      const std::vector<std::string>& flag_keys) {
  Options o;
  for (size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    if (a.rfind("--", 0) != 0) {
      o.positional.push_back(a);
      continue;
    }
    std::string key = a, value;
    const size_t eq = a.find('=');
    bool has_value = false;
    if (eq != std::string::npos) {
      key = a.substr(0, eq);
      value = a.substr(eq + 1);
      has_value = true;
    }
    bool is_value = false, is_flag = false;
    for (const auto& k : value_keys) is_value |= (k == key);
    for (const auto& k : flag_keys) is_flag |= (k == key);
    if ((is_flag || is_value) && (o.get(key) || o.flag(key)))
      throw std::invalid_argument("option " + key + " given twice");
    if (is_flag && !has_value) {
      o.flags.push_back(key);
    } else if (is_value) {
      if (!has_value) {
        if (i + 1 >= args.size()) throw std::invalid_argument("option " + key + " needs a value");
        value = args[++i];
      }
      o.values.emplace_back(key, value);
    } else {
      throw std::invalid_argument("unknown option " + key);
    }
  }
  return o;
}

double parse_double(const std::string& key, const std::string& value, double lo, double hi) {
  size_t pos = 0;
  double v = 0;
  try {
    v = std::stod(value, &pos);
  } catch (...) {
    pos = 0;
  }
  if (pos != value.size() || value.empty() || !(v >= lo && v <= hi)) {
    std::ostringstream os;
    os << key << " expects a number in [" << lo << ", " << hi << "], got '" << value << "'";
    throw std::invalid_argument(os.str());
  }
  return v;
}

int parse_int(const std::string& key, const std::string& value, int lo, int hi) {
  size_t pos = 0;
  long v = 0;
  try {
    v = std::stol(value, &pos);
  } catch (...) {
    pos = 0;
  }
  if (pos != value.size() || value.empty() || v < lo || v > hi)
    throw std::invalid_argument(key + " expects an integer in [" + std::to_string(lo) + ", " +
                                std::to_string(hi) + "], got '" + value + "'");
  return int(v);
}

std::string printable(const std::string& s) {
  std::string out;
  out.reserve(s.size());
  for (const char ch : s) {
    const unsigned char c = static_cast<unsigned char>(ch);
    if (c < 0x20 || c == 0x7f) {
      char esc[8];
      std::snprintf(esc, sizeof esc, "\\x%02x", c);
      out += esc;
    } else {
      out += ch;
    }
  }
  return out;
}

std::string g_phase = "starting";

double g_age_at_main = -1;

double process_age_seconds() {
#ifdef __linux__
  std::ifstream in("/proc/self/stat");
  std::string stat;
  std::getline(in, stat);
  // Field 22, starttime in clock ticks after boot; fields 3.. follow the ")" ending the name.
  const std::size_t close = stat.rfind(')');
  if (close == std::string::npos) return -1;
  std::istringstream fields(stat.substr(close + 2));
  std::string f;
  for (int k = 3; k <= 22 && fields >> f; ++k)
    if (k == 22) {
      const long tick = ::sysconf(_SC_CLK_TCK);
      timespec now{};
      if (tick <= 0 || ::clock_gettime(CLOCK_BOOTTIME, &now) != 0) return -1;
      return double(now.tv_sec) + 1e-9 * double(now.tv_nsec) - std::stod(f) / double(tick);
    }
#endif
  return -1;
}

double process_cpu_seconds() {
  timespec t{};
  if (::clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t) != 0) return -1;
  return double(t.tv_sec) + 1e-9 * double(t.tv_nsec);
}

void set_phase(const std::string& phase) {
  g_phase = phase;
}

const std::string& current_phase() {
  return g_phase;
}

}  // namespace amalgam::cli
