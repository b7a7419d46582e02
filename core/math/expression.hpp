// A small, safe expression language for scene inputs given as functions of position and time
// (e.g. an initial velocity "1e-3*cos(pi*x/0.01)"). Grammar, loosest binding first:
//   expr    := term (('+' | '-') term)*
//   term    := unary (('*' | '/') unary)*
//   unary   := ('+' | '-') unary | power
//   power   := primary ('^' unary)?            right-associative; -x^2 = -(x^2), 2^-1 = 0.5
//   primary := number | x | y | z | t | pi | e | name '(' expr (',' expr)* ')' | '(' expr ')'
// Numbers are decimal (1, .5, 2., 1e-3); functions are sin cos tan asin acos atan exp log sqrt
// abs floor ceil (one argument), atan2(y,x) min max pow (two) and clamp(v,lo,hi) (three; it is
// min(max(v,lo),hi)). Spaces, tabs and line breaks are allowed between tokens. Limits: at most
// 4096 characters and 64 levels of nesting (parentheses, calls, unary signs, exponents); any
// other control character, an unknown name, a wrong argument count or a literal that overflows
// is an InputError naming the 1-based character position. The text compiles to a flat postfix
// program whose stack depth is known at parse time, so eval needs no allocation; it uses plain
// double arithmetic and <cmath> only, and may return NaN or inf (log(-1)): the caller checks.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "core/math/types.hpp"

namespace amalgam {

class Expression {
 public:
  static constexpr std::size_t kMaxLength = 4096;
  static constexpr int kMaxNesting = 64;
  // At most 4 values wait per nesting level ("x+x*clamp(x,x,(...))"), so this is never reached.
  static constexpr int kMaxStack = 4 * kMaxNesting + 8;

  Expression() = default;  // the constant 0
  // Parses `text`; throws InputError "at character N: <reason>".
  static Expression parse(const std::string& text);
  double eval(double x, double y, double z, double t) const;  // pure, thread-safe, no allocation
  bool uses_time() const { return uses_time_; }
  bool is_constant() const { return is_constant_; }
  const std::string& text() const { return text_; }

  // The compiled form (for the parser and evaluator).
  // clang-format off
  enum class Code : std::uint8_t {
    Num, X, Y, Z, T,                                                          // push
    Neg, Sin, Cos, Tan, Asin, Acos, Atan, Exp, Log, Sqrt, Abs, Floor, Ceil,   // 1 -> 1
    Add, Sub, Mul, Div, Pow, Atan2, Min, Max,                                 // 2 -> 1
    Clamp                                                                     // 3 -> 1
  };
  // clang-format on
  struct Op {
    Code code;
    double value;  // Num only
  };

 private:
  friend class ExpressionParser;
  std::string text_ = "0";
  std::vector<Op> program_{{Code::Num, 0.0}};
  bool uses_time_ = false;
  bool is_constant_ = true;
};

// A vector given per particle as three expressions of its position x, y, z (core/math/
// expression.hpp), e.g. an initial velocity ["0", "0", "1e-3*cos(pi*x/0.01)"], and for a
// boundary condition of the time t too; `where` is the scene path for messages
// ("scene.json: /objects/0/velocity").
struct VectorField {
  Expression c[3];
  std::string where;
  Vec3d at(const Vec3d& x, double t = 0) const {
    return Vec3d(c[0].eval(x[0], x[1], x[2], t), c[1].eval(x[0], x[1], x[2], t),
                 c[2].eval(x[0], x[1], x[2], t));
  }
  bool uses_time() const { return c[0].uses_time() || c[1].uses_time() || c[2].uses_time(); }
  bool is_constant() const {
    return c[0].is_constant() && c[1].is_constant() && c[2].is_constant();
  }
};

}  // namespace amalgam
