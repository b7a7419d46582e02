#include "io/json_reader.hpp"

#include <cmath>
#include <climits>
#include <cstdio>
#include <limits>
#include <sstream>

namespace amalgam::detail {

namespace {
std::string type_name(const nlohmann::json& v) {
  return v.type_name();
}
std::string show(const nlohmann::json& v) {
  return show_json(v);
}

// Appends a preview of v to out, stopping near `limit` characters and 4 levels down (dump() of a
// deeply nested value would recurse once per level).
void preview(const nlohmann::json& v, std::string& out, std::size_t limit, int depth) {
  if (out.size() > limit) return;
  if (!v.is_structured()) {
    out += v.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace);
    return;
  }
  const bool obj = v.is_object();
  out += obj ? '{' : '[';
  if (depth >= 4 && !v.empty()) {
    out += "...";
  } else {
    bool first = true;
    for (auto it = v.begin(); it != v.end() && out.size() <= limit; ++it) {
      if (!first) out += ',';
      first = false;
      if (obj)
        out += nlohmann::json(it.key()).dump(-1, ' ', false,
                                             nlohmann::json::error_handler_t::replace) +
               ':';
      preview(*it, out, limit, depth + 1);
    }
  }
  out += obj ? '}' : ']';
}
std::string fmt(double x) {
  std::ostringstream os;
  os << x;
  return os.str();
}

// The JSON path of the value being parsed, from the parser's events.
class PathTracker {
 public:
  struct Level {
    bool object;
    std::set<std::string> keys;
    std::string key;    // object: the key whose value is being parsed
    std::size_t index;  // array: the element being parsed
  };
  std::vector<Level> levels;

  std::string path(std::size_t upto) const {
    std::string p;
    for (std::size_t i = 0; i < upto && i < levels.size(); ++i) {
      if (p.size() > 40) return p + "/...";
      p += "/" + (levels[i].object ? levels[i].key : std::to_string(levels[i].index));
    }
    return p.empty() ? "/" : p;
  }
  void element_done() {
    if (!levels.empty() && !levels.back().object) ++levels.back().index;
  }
};
// A number the scene gives becomes a Real: in the float build it must be a normal float (or 0),
// else it silently turns into 0, a denormal or infinity at run time.
bool representable(double x) {
  if (sizeof(Real) == sizeof(double) || x == 0) return true;
  const double a = std::abs(x);
  return a >= double(std::numeric_limits<float>::min()) &&
         a <= double(std::numeric_limits<float>::max());
}
std::string float_range() {
  return "a normal float, magnitude in [" + fmt(double(std::numeric_limits<float>::min())) + ", " +
         fmt(double(std::numeric_limits<float>::max())) + "] (this build's precision)";
}
}  // namespace

std::string show_json(const nlohmann::json& v) {
  std::string s;
  preview(v, s, 60, 0);
  if (s.size() > 60) s = s.substr(0, 57) + "...";
  return s;
}

nlohmann::json parse_json_strict(const std::string& text, const std::string& file) {
  PathTracker t;
  using E = nlohmann::json::parse_event_t;
  auto cb = [&](int, E event, nlohmann::json& parsed) -> bool {
    switch (event) {
      case E::object_start:
      case E::array_start:
        if (t.levels.size() >= std::size_t(kMaxJsonDepth))
          throw InputError(file + ": " + t.path(t.levels.size()) + ": nested deeper than " +
                           std::to_string(kMaxJsonDepth) + " levels");
        t.levels.push_back({event == E::object_start, {}, "", 0});
        break;
      case E::key: {
        auto& top = t.levels.back();
        top.key = parsed.get<std::string>();
        if (!top.keys.insert(top.key).second)
          throw InputError(file + ": " + t.path(t.levels.size()) +
                           ": key given twice in the same object");
        break;
      }
      case E::object_end:
      case E::array_end:
        t.levels.pop_back();
        t.element_done();
        break;
      case E::value:
        t.element_done();
        break;
    }
    return true;
  };
  try {
    return nlohmann::json::parse(text, cb);
  } catch (const nlohmann::json::exception& e) {  // parse_error, out_of_range (1e999), ...
    throw InputError(file + ": not valid JSON: " + e.what());
  }
}

JsonObject::JsonObject(const nlohmann::json& j, std::string file, std::string path)
    : j_(j), file_(std::move(file)), path_(std::move(path)) {
  if (!j_.is_object())
    throw InputError(file_ + ": " + (path_.empty() ? "/" : path_) + ": expected an object, got " +
                     type_name(j_));
}

void JsonObject::fail(const std::string& key, const std::string& what) const {
  throw InputError(where(key) + ": " + what);
}

const nlohmann::json& JsonObject::at(const std::string& key) {
  used_.insert(key);
  return j_.at(key);
}

double JsonObject::check_number(const std::string& key, const nlohmann::json& v, double lo,
                                double hi, bool lo_open) {
  const std::string range =
      std::string("a number in ") + (lo_open ? "(" : "[") + fmt(lo) + ", " + fmt(hi) + "]";
  if (!v.is_number()) fail(key, "expected " + range + ", got " + type_name(v) + " " + show(v));
  const double x = v.get<double>();
  if (!std::isfinite(x)) fail(key, "expected a finite number, got " + show(v));
  if (x < lo || x > hi || (lo_open && x == lo)) fail(key, "expected " + range + ", got " + fmt(x));
  if (!representable(x)) fail(key, fmt(x) + " is not " + float_range());
  return x;
}

double JsonObject::number(const std::string& key, double def, double lo, double hi, bool lo_open) {
  if (!has(key)) return def;
  return check_number(key, at(key), lo, hi, lo_open);
}

double JsonObject::required_number(const std::string& key, double lo, double hi, bool lo_open) {
  if (!has(key)) fail(key, "missing required number");
  return check_number(key, at(key), lo, hi, lo_open);
}

long long JsonObject::integer(const std::string& key, long long def, long long lo, long long hi) {
  if (!has(key)) return def;
  const auto& v = at(key);
  if (!v.is_number_integer() ||
      (v.is_number_unsigned() && v.get<unsigned long long>() > (unsigned long long)LLONG_MAX))
    fail(key, "expected an integer in [" + std::to_string(lo) + ", " + std::to_string(hi) +
                  "], got " + show(v));
  const long long x = v.get<long long>();
  if (x < lo || x > hi)
    fail(key, "expected an integer in [" + std::to_string(lo) + ", " + std::to_string(hi) +
                  "], got " + std::to_string(x));
  return x;
}

bool JsonObject::boolean(const std::string& key, bool def) {
  if (!has(key)) return def;
  const auto& v = at(key);
  if (!v.is_boolean()) fail(key, "expected true or false, got " + show(v));
  return v.get<bool>();
}

std::string JsonObject::string(const std::string& key, const std::string& def) {
  if (!has(key)) return def;
  const auto& v = at(key);
  if (!v.is_string()) fail(key, "expected a string, got " + type_name(v) + " " + show(v));
  return v.get<std::string>();
}

std::string JsonObject::choice(const std::string& key, const std::string& def,
                               const std::vector<std::string>& allowed) {
  const std::string s = string(key, def);
  for (const auto& a : allowed)
    if (a == s) return s;
  std::string list;
  for (size_t i = 0; i < allowed.size(); ++i) list += (i ? ", " : "") + allowed[i];
  fail(key, "unknown value \"" + s + "\" (expected one of: " + list + ")");
}

std::vector<std::string> JsonObject::strings(const std::string& key,
                                             const std::vector<std::string>& def) {
  if (!has(key)) return def;
  const auto& v = at(key);
  if (!v.is_array()) fail(key, "expected an array of strings, got " + type_name(v) + " " + show(v));
  std::vector<std::string> out;
  for (size_t i = 0; i < v.size(); ++i) {
    if (!v[i].is_string())
      fail(key + "/" + std::to_string(i),
           "expected a string, got " + type_name(v[i]) + " " + show(v[i]));
    out.push_back(v[i].get<std::string>());
  }
  return out;
}

Vec3 JsonObject::vec3(const std::string& key, const Vec3& def) {
  if (!has(key)) return def;
  return required_vec3(key);
}

Vec3 JsonObject::required_vec3(const std::string& key) {
  if (!has(key)) fail(key, "missing required [x, y, z] array");
  const auto& v = at(key);
  if (!v.is_array() || v.size() != 3) fail(key, "expected an array of 3 numbers, got " + show(v));
  Vec3 r;
  for (int a = 0; a < 3; ++a) {
    if (!v[size_t(a)].is_number())
      fail(key + "/" + std::to_string(a), "expected a number, got " + show(v[size_t(a)]));
    const double x = v[size_t(a)].get<double>();
    if (!std::isfinite(x))
      fail(key + "/" + std::to_string(a), "expected a finite number, got " + show(v[size_t(a)]));
    if (!representable(x)) fail(key + "/" + std::to_string(a), fmt(x) + " is not " + float_range());
    r[a] = Real(x);
  }
  return r;
}

bool JsonObject::has_expressions(const std::string& key) const {
  if (!has(key) || !j_.at(key).is_array()) return false;
  for (const auto& e : j_.at(key))
    if (e.is_string()) return true;
  return false;
}

std::shared_ptr<const VectorField> JsonObject::vector_field(const std::string& key) {
  if (!has(key)) return nullptr;
  const auto& v = at(key);
  if (!v.is_array() || v.size() != 3)
    fail(key, "expected an array of 3 numbers or expressions, got " + show(v));
  auto f = std::make_shared<VectorField>();
  f->where = where(key);
  for (int a = 0; a < 3; ++a) {
    const auto& e = v[size_t(a)];
    const std::string k = key + "/" + std::to_string(a);
    std::string text;
    if (e.is_number()) {
      const double x = e.get<double>();
      if (!std::isfinite(x)) fail(k, "expected a finite number, got " + show(e));
      char buf[32];
      std::snprintf(buf, sizeof buf, "%.17g", x);
      text = buf;
    } else if (e.is_string()) {
      text = e.get<std::string>();
    } else {
      fail(k, "expected a number or an expression of x, y, z, got " + show(e));
    }
    try {
      f->c[a] = Expression::parse(text);
    } catch (const InputError& err) {
      fail(k, std::string("expression ") + show(e) + ": " + err.what());
    }
    if (f->c[a].uses_time()) fail(k, "an initial value cannot depend on t");
  }
  return f;
}

JsonObject JsonObject::object(const std::string& key) {
  static const nlohmann::json empty = nlohmann::json::object();
  if (!has(key)) return JsonObject(empty, file_, path_ + "/" + key);
  const auto& v = at(key);
  if (!v.is_object()) fail(key, "expected an object, got " + type_name(v));
  return JsonObject(v, file_, path_ + "/" + key);
}

std::vector<JsonObject> JsonObject::objects(const std::string& key) {
  std::vector<JsonObject> out;
  if (!has(key)) return out;
  const auto& v = at(key);
  if (!v.is_array()) fail(key, "expected an array of objects, got " + type_name(v));
  for (size_t i = 0; i < v.size(); ++i)
    out.emplace_back(v[i], file_, path_ + "/" + key + "/" + std::to_string(i));
  return out;
}

std::vector<std::string> JsonObject::keys() const {
  std::vector<std::string> k;
  for (auto it = j_.begin(); it != j_.end(); ++it) k.push_back(it.key());
  return k;
}

void JsonObject::finish() const {
  for (auto it = j_.begin(); it != j_.end(); ++it)
    if (!used_.count(it.key()))
      fail(it.key(), "unknown key (check the spelling against docs/scenes.md)");
}

}  // namespace amalgam::detail
