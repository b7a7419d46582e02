// Strict reader over an nlohmann::json object that knows its file and JSON path: typed getters
// with defaults and ranges, and finish() rejecting unknown keys. Internal to io/.
#pragma once

#include <memory>
#include <nlohmann/json.hpp>
#include <set>
#include <string>
#include <vector>

#include "core/errors.hpp"
#include "core/math/expression.hpp"
#include "core/math/types.hpp"

namespace amalgam::detail {

// Deepest nesting of arrays and objects a scene may have (real scenes use under 10).
constexpr int kMaxJsonDepth = 64;

// Parses JSON text the way a scene needs it: InputError naming the file (and the JSON path where
// it is known) for malformed text, a key given twice in one object, or nesting deeper than
// kMaxJsonDepth (which also bounds every later recursion over the document).
nlohmann::json parse_json_strict(const std::string& text, const std::string& file);

// A value for a message: at most ~60 characters, at most a few levels deep, control characters
// escaped.
std::string show_json(const nlohmann::json& v);

class JsonObject {
 public:
  JsonObject(const nlohmann::json& j, std::string file, std::string path);

  bool has(const std::string& key) const { return j_.contains(key); }
  bool has_object(const std::string& key) const { return has(key) && j_.at(key).is_object(); }
  bool has_string(const std::string& key) const { return has(key) && j_.at(key).is_string(); }
  double number(const std::string& key, double def, double lo, double hi, bool lo_open = false);
  double required_number(const std::string& key, double lo, double hi, bool lo_open = false);
  long long integer(const std::string& key, long long def, long long lo, long long hi);
  bool boolean(const std::string& key, bool def);
  std::string string(const std::string& key, const std::string& def);
  std::string choice(const std::string& key, const std::string& def,
                     const std::vector<std::string>& allowed);
  // An array of strings (`def` when absent); an entry that is not a string fails at key/index.
  std::vector<std::string> strings(const std::string& key, const std::vector<std::string>& def);
  Vec3 vec3(const std::string& key, const Vec3& def);
  Vec3 required_vec3(const std::string& key);
  // An [x, y, z] array whose entries are numbers or expressions of x, y, z (strings,
  // core/math/expression.hpp); null when absent. With `time` they may use t too (a boundary
  // condition); without it t is an error (initial values).
  std::shared_ptr<const VectorField> vector_field(const std::string& key, bool time = false);
  // Whether `key` is an array holding at least one string (an expression).
  bool has_expressions(const std::string& key) const;
  JsonObject object(const std::string& key);
  std::vector<JsonObject> objects(const std::string& key);  // array of objects; empty if absent
  std::vector<std::string> keys() const;
  // Throws if the object has keys no getter asked for.
  void finish() const;

  [[noreturn]] void fail(const std::string& key, const std::string& what) const;
  std::string where(const std::string& key) const { return file_ + ": " + path_ + "/" + key; }

 private:
  const nlohmann::json& j_;
  std::string file_, path_;
  std::set<std::string> used_;
  const nlohmann::json& at(const std::string& key);
  double check_number(const std::string& key, const nlohmann::json& v, double lo, double hi,
                      bool lo_open);
};

}  // namespace amalgam::detail
