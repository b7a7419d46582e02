// Recursive-descent parser to a postfix program, and its evaluator (grammar in expression.hpp).
#include "core/math/expression.hpp"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdio>

#include "core/errors.hpp"

namespace amalgam {

namespace {

using Code = Expression::Code;

struct Function {
  const char* name;
  Code code;
  int arity;
};
constexpr Function kFunctions[] = {
    {"sin", Code::Sin, 1},     {"cos", Code::Cos, 1},     {"tan", Code::Tan, 1},
    {"asin", Code::Asin, 1},   {"acos", Code::Acos, 1},   {"atan", Code::Atan, 1},
    {"exp", Code::Exp, 1},     {"log", Code::Log, 1},     {"sqrt", Code::Sqrt, 1},
    {"abs", Code::Abs, 1},     {"floor", Code::Floor, 1}, {"ceil", Code::Ceil, 1},
    {"atan2", Code::Atan2, 2}, {"min", Code::Min, 2},     {"max", Code::Max, 2},
    {"pow", Code::Pow, 2},     {"clamp", Code::Clamp, 3}};

bool is_space(char c) {
  return c == ' ' || c == '\t' || c == '\n' || c == '\r';
}
bool is_digit(char c) {
  return c >= '0' && c <= '9';
}
bool is_alpha(char c) {
  return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || c == '_';
}

// Net stack change of one op.
int stack_effect(Code c) {
  return c <= Code::T ? 1 : c <= Code::Ceil ? 0 : c == Code::Clamp ? -2 : -1;
}

// A decimal literal that from_chars found out of range: does it overflow (an error) rather than
// underflow (to zero)? It overflows when its first non-zero digit stands at 10^1 or above.
bool overflows(const std::string& lit) {
  std::size_t i = 0;
  long int_digits = 0, frac_zeros = 0;  // integer digits from the first non-zero one; zeros after
  bool point = false, frac_nonzero = false;  // the point before the first non-zero digit
  for (; i < lit.size() && lit[i] != 'e' && lit[i] != 'E'; ++i) {
    if (lit[i] == '.') {
      point = true;
    } else if (!point) {
      int_digits += int_digits > 0 || lit[i] != '0';
    } else if (int_digits == 0 && !frac_nonzero) {
      frac_nonzero = lit[i] != '0';
      frac_zeros += !frac_nonzero;
    }
  }
  long exp10 = 0;
  if (i < lit.size()) {
    const bool neg = lit[i + 1] == '-';
    for (i += 1 + (lit[i + 1] == '-' || lit[i + 1] == '+'); i < lit.size(); ++i)
      exp10 = std::min(exp10 * 10 + (lit[i] - '0'), 1000000L);
    if (neg) exp10 = -exp10;
  }
  const long order = int_digits > 0 ? int_digits - 1 : -(frac_zeros + 1);
  return (int_digits > 0 || frac_nonzero) && order + exp10 > 0;
}

}  // namespace

class ExpressionParser {
 public:
  explicit ExpressionParser(const std::string& s) : s_(s) { out_.program_.clear(); }

  Expression run() {
    if (s_.size() > Expression::kMaxLength)
      fail(Expression::kMaxLength, "expression longer than 4096 characters");
    for (std::size_t k = 0; k < s_.size(); ++k) {
      const unsigned char c = static_cast<unsigned char>(s_[k]);
      if ((c < 0x20 && !is_space(s_[k])) || c == 0x7f)
        fail(k, "control character (code " + std::to_string(int(c)) + ")");
    }
    skip();
    if (i_ == s_.size()) fail(i_, "empty expression");
    expr();
    if (i_ < s_.size()) fail(i_, "unexpected " + describe(i_) + " after the expression");
    out_.text_ = s_;
    return out_;
  }

 private:
  [[noreturn]] void fail(std::size_t pos, const std::string& why) const {
    throw InputError("at character " + std::to_string(pos + 1) + ": " + why);
  }
  std::string describe(std::size_t pos) const {
    if (pos >= s_.size()) return "end of text";
    const unsigned char c = static_cast<unsigned char>(s_[pos]);
    if (c > 0x20 && c < 0x7f) return std::string("'") + char(c) + "'";
    char buf[16];
    std::snprintf(buf, sizeof buf, "byte 0x%02x", unsigned(c));
    return buf;
  }
  void skip() {
    while (i_ < s_.size() && is_space(s_[i_])) ++i_;
  }
  bool accept(char c) {
    skip();
    if (i_ < s_.size() && s_[i_] == c) {
      ++i_;
      return true;
    }
    return false;
  }
  void expect(char c) {
    if (!accept(c)) fail(i_, std::string("expected '") + c + "', found " + describe(i_));
  }
  void emit(Code c, double v = 0) {
    out_.program_.push_back({c, v});
    depth_ += stack_effect(c);
    if (depth_ > Expression::kMaxStack) fail(i_, "expression too deeply nested");
  }
  // Every recursion cycle passes through here, which bounds the parser's stack.
  void enter(std::size_t pos) {
    if (++nest_ > Expression::kMaxNesting) fail(pos, "nesting deeper than 64 levels");
  }

  void expr() {
    term();
    for (;;) {
      if (accept('+')) {
        term();
        emit(Code::Add);
      } else if (accept('-')) {
        term();
        emit(Code::Sub);
      } else {
        return;
      }
    }
  }
  void term() {
    unary();
    for (;;) {
      if (accept('*')) {
        unary();
        emit(Code::Mul);
      } else if (accept('/')) {
        unary();
        emit(Code::Div);
      } else {
        return;
      }
    }
  }
  void unary() {
    skip();
    const std::size_t pos = i_;
    if (accept('+') || accept('-')) {
      const bool neg = s_[pos] == '-';
      enter(pos);
      unary();
      --nest_;
      if (neg) emit(Code::Neg);
    } else {
      primary();
      if (accept('^')) {
        enter(i_ - 1);
        unary();
        --nest_;
        emit(Code::Pow);
      }
    }
  }
  void primary() {
    skip();
    const std::size_t pos = i_;
    if (i_ == s_.size()) fail(i_, "unexpected end of text");
    const char c = s_[i_];
    if (is_digit(c) || (c == '.' && i_ + 1 < s_.size() && is_digit(s_[i_ + 1]))) return number();
    if (c == '(') {
      ++i_;
      enter(pos);
      expr();
      expect(')');
      --nest_;
      return;
    }
    if (!is_alpha(c)) fail(i_, "unexpected " + describe(i_));
    while (i_ < s_.size() && (is_alpha(s_[i_]) || is_digit(s_[i_]))) ++i_;
    const std::string name = s_.substr(pos, i_ - pos);
    static constexpr const char* kVars[] = {"x", "y", "z", "t"};
    for (int k = 0; k < 4; ++k)
      if (name == kVars[k]) {
        out_.is_constant_ = false;
        out_.uses_time_ |= k == 3;
        return emit(Code(int(Code::X) + k));
      }
    if (name == "pi") return emit(Code::Num, 3.14159265358979323846);
    if (name == "e") return emit(Code::Num, 2.71828182845904523536);
    for (const Function& f : kFunctions) {
      if (name != f.name) continue;
      if (!accept('(')) fail(i_, "expected '(' after '" + name + "'");
      enter(pos);
      const auto arity_error = [&](const std::string& got) {
        fail(pos, "'" + name + "' takes " + std::to_string(f.arity) + " argument" +
                      (f.arity > 1 ? "s" : "") + ", got " + got);
      };
      int args = 1;
      expr();
      for (; accept(','); ++args) {
        if (args == f.arity) arity_error("more");
        expr();
      }
      if (args != f.arity) arity_error(std::to_string(args));
      expect(')');
      --nest_;
      return emit(f.code);
    }
    fail(pos, "unknown name '" + name + "'");
  }
  void number() {
    const std::size_t pos = i_;
    while (i_ < s_.size() && is_digit(s_[i_])) ++i_;
    if (i_ < s_.size() && s_[i_] == '.') ++i_;
    while (i_ < s_.size() && is_digit(s_[i_])) ++i_;
    if (i_ < s_.size() && (s_[i_] == 'e' || s_[i_] == 'E')) {
      std::size_t k = i_ + 1;
      if (k < s_.size() && (s_[k] == '+' || s_[k] == '-')) ++k;
      if (k == s_.size() || !is_digit(s_[k])) fail(i_, "exponent without digits");
      for (i_ = k; i_ < s_.size() && is_digit(s_[i_]);) ++i_;
    }
    double v = 0;
    const auto r = std::from_chars(s_.data() + pos, s_.data() + i_, v);
    if (r.ec == std::errc::result_out_of_range) {
      if (overflows(s_.substr(pos, i_ - pos))) fail(pos, "number out of range");
      v = 0;
    } else if (r.ec != std::errc() || r.ptr != s_.data() + i_ || !std::isfinite(v)) {
      fail(pos, "malformed number");
    }
    emit(Code::Num, v);
  }

  const std::string& s_;
  std::size_t i_ = 0;
  int nest_ = 0, depth_ = 0;
  Expression out_;
};

Expression Expression::parse(const std::string& text) {
  return ExpressionParser(text).run();
}

double Expression::eval(double x, double y, double z, double t) const {
  double st[kMaxStack];
  int n = 0;
  for (const Op& op : program_) {
    if (op.code <= Code::T) {  // a push
      const double v[] = {op.value, x, y, z, t};
      st[n++] = v[int(op.code)];
      continue;
    }
    double& a = st[n - 1];
    // clang-format off
    switch (op.code) {
      case Code::Neg: a = -a; break;
      case Code::Sin: a = std::sin(a); break;
      case Code::Cos: a = std::cos(a); break;
      case Code::Tan: a = std::tan(a); break;
      case Code::Asin: a = std::asin(a); break;
      case Code::Acos: a = std::acos(a); break;
      case Code::Atan: a = std::atan(a); break;
      case Code::Exp: a = std::exp(a); break;
      case Code::Log: a = std::log(a); break;
      case Code::Sqrt: a = std::sqrt(a); break;
      case Code::Abs: a = std::fabs(a); break;
      case Code::Floor: a = std::floor(a); break;
      case Code::Ceil: a = std::ceil(a); break;
      case Code::Clamp: n -= 2; st[n - 1] = std::fmin(std::fmax(st[n - 1], st[n]), st[n + 1]); break;
      default: {
        const double b = st[--n];
        double& l = st[n - 1];
        switch (op.code) {
          case Code::Add: l += b; break;
          case Code::Sub: l -= b; break;
          case Code::Mul: l *= b; break;
          case Code::Div: l /= b; break;
          case Code::Pow: l = std::pow(l, b); break;
          case Code::Atan2: l = std::atan2(l, b); break;
          case Code::Min: l = std::fmin(l, b); break;
          case Code::Max: l = std::fmax(l, b); break;
          default: break;
        }
      }
    }
    // clang-format on
  }
  return st[0];
}

}  // namespace amalgam
