// The scene-input expression language (issue 27): values, precedence and associativity, every
// function, the flags, each error naming its position, the limits, and random hostile strings
// that may only parse or throw InputError.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <functional>
#include <random>
#include <string>

#include "core/errors.hpp"
#include "core/math/expression.hpp"

using namespace amalgam;

namespace {

constexpr double kPi = 3.14159265358979323846;

double ev(const std::string& s, double x = 0, double y = 0, double z = 0, double t = 0) {
  return Expression::parse(s).eval(x, y, z, t);
}

// The message of the InputError that parsing `s` throws ("" when it parses).
std::string error_of(const std::string& s) {
  try {
    Expression::parse(s);
  } catch (const InputError& e) {
    return e.what();
  }
  return "";
}

std::string repeat(const std::string& s, int n) {
  std::string r;
  for (int i = 0; i < n; ++i) r += s;
  return r;
}

}  // namespace

TEST(Expression, NumbersAndConstants) {
  EXPECT_EQ(ev("42"), 42.0);
  EXPECT_EQ(ev(".5"), 0.5);
  EXPECT_EQ(ev("2."), 2.0);
  EXPECT_EQ(ev("1e-3"), 1e-3);
  EXPECT_EQ(ev("1.5E+2"), 150.0);
  EXPECT_EQ(ev("0e999999"), 0.0);
  EXPECT_EQ(ev("1e-310"), 1e-310);  // subnormal
  EXPECT_EQ(ev("1e-400"), 0.0);     // underflow is zero, not an error
  EXPECT_EQ(ev("0.000" + std::string(400, '0') + "1"), 0.0);
  EXPECT_EQ(ev("pi"), kPi);
  EXPECT_EQ(ev("e"), std::exp(1.0));
  EXPECT_EQ(ev(" \t1 +\n2\r "), 3.0);
}

TEST(Expression, Variables) {
  EXPECT_EQ(ev("x", 1, 2, 3, 4), 1.0);
  EXPECT_EQ(ev("y", 1, 2, 3, 4), 2.0);
  EXPECT_EQ(ev("z", 1, 2, 3, 4), 3.0);
  EXPECT_EQ(ev("t", 1, 2, 3, 4), 4.0);
  EXPECT_EQ(ev("x*100+y*10+z-t", 1, 2, 3, 4), 119.0);
}

TEST(Expression, PrecedenceAndAssociativity) {
  EXPECT_EQ(ev("1+2*3"), 7.0);
  EXPECT_EQ(ev("(1+2)*3"), 9.0);
  EXPECT_EQ(ev("1-2-3"), -4.0);
  EXPECT_EQ(ev("8/4/2"), 1.0);
  EXPECT_EQ(ev("2*3^2"), 18.0);
  EXPECT_EQ(ev("2^3^2"), 512.0);  // right-associative
  EXPECT_EQ(ev("(2^3)^2"), 64.0);
  EXPECT_EQ(ev("-2^2"), -4.0);  // -(2^2)
  EXPECT_EQ(ev("(-2)^2"), 4.0);
  EXPECT_EQ(ev("-x^2", 3), -9.0);
  EXPECT_EQ(ev("2^-1"), 0.5);
  EXPECT_EQ(ev("2^-1^2"), 0.5);  // 2^(-(1^2))
  EXPECT_EQ(ev("--3"), 3.0);
  EXPECT_EQ(ev("+-+3"), -3.0);
  EXPECT_EQ(ev("1 - -1"), 2.0);
  EXPECT_EQ(ev("2*-3"), -6.0);
  EXPECT_EQ(ev("-(1+2)*3"), -9.0);
}

TEST(Expression, EveryFunction) {
  const double a = 0.3, b = -1.7;
  EXPECT_EQ(ev("sin(x)", a), std::sin(a));
  EXPECT_EQ(ev("cos(x)", a), std::cos(a));
  EXPECT_EQ(ev("tan(x)", a), std::tan(a));
  EXPECT_EQ(ev("asin(x)", a), std::asin(a));
  EXPECT_EQ(ev("acos(x)", a), std::acos(a));
  EXPECT_EQ(ev("atan(x)", a), std::atan(a));
  EXPECT_EQ(ev("atan2(x, y)", a, b), std::atan2(a, b));
  EXPECT_EQ(ev("exp(x)", a), std::exp(a));
  EXPECT_EQ(ev("log(x)", a), std::log(a));
  EXPECT_EQ(ev("sqrt(x)", a), std::sqrt(a));
  EXPECT_EQ(ev("abs(y)", a, b), 1.7);
  EXPECT_EQ(ev("floor(y)", a, b), -2.0);
  EXPECT_EQ(ev("ceil(y)", a, b), -1.0);
  EXPECT_EQ(ev("min(x, y)", a, b), b);
  EXPECT_EQ(ev("max(x, y)", a, b), a);
  EXPECT_EQ(ev("pow(2, 10)"), 1024.0);
  EXPECT_EQ(ev("clamp(5, 0, 1)"), 1.0);
  EXPECT_EQ(ev("clamp(-5, 0, 1)"), 0.0);
  EXPECT_EQ(ev("clamp(0.25, 0, 1)"), 0.25);
  EXPECT_EQ(ev("max(min(x,1),-1) + sin(cos(2*x))", a), std::sin(std::cos(2 * a)) + a);
  // Non-finite results are returned, for the caller to check.
  EXPECT_TRUE(std::isnan(ev("log(-1)")));
  EXPECT_TRUE(std::isinf(ev("1/0")));
}

TEST(Expression, IssueExampleIsBitwiseTheDirectFormula) {
  const Expression e = Expression::parse("1e-3*cos(pi*x/0.01)");
  for (double x : {0.0, 0.001, 0.0025, 0.005, -0.0125, 0.3})
    EXPECT_EQ(e.eval(x, 1, 2, 3), 1e-3 * std::cos(kPi * x / 0.01)) << x;
  EXPECT_EQ(e.eval(0, 0, 0, 0), 1e-3);
  EXPECT_EQ(e.text(), "1e-3*cos(pi*x/0.01)");
}

TEST(Expression, Flags) {
  EXPECT_TRUE(Expression::parse("2*pi+e").is_constant());
  EXPECT_FALSE(Expression::parse("2*pi+e").uses_time());
  EXPECT_FALSE(Expression::parse("x+1").is_constant());
  EXPECT_FALSE(Expression::parse("x+y+z").uses_time());
  EXPECT_TRUE(Expression::parse("sin(t)").uses_time());
  EXPECT_FALSE(Expression::parse("sin(t)").is_constant());
  const Expression zero;  // default: the constant 0
  EXPECT_EQ(zero.eval(1, 2, 3, 4), 0.0);
  EXPECT_TRUE(zero.is_constant());
}

TEST(Expression, ErrorsNameThePositionAndReason) {
  EXPECT_EQ(error_of(""), "at character 1: empty expression");
  EXPECT_EQ(error_of("   "), "at character 4: empty expression");
  EXPECT_EQ(error_of("sinx"), "at character 1: unknown name 'sinx'");
  EXPECT_EQ(error_of("1 + foo(2)"), "at character 5: unknown name 'foo'");
  EXPECT_EQ(error_of("(1+2"), "at character 5: expected ')', found end of text");
  EXPECT_EQ(error_of("1+2)"), "at character 4: unexpected ')' after the expression");
  EXPECT_EQ(error_of("1 2"), "at character 3: unexpected '2' after the expression");
  EXPECT_EQ(error_of("1.2.3"), "at character 4: unexpected '.' after the expression");
  EXPECT_EQ(error_of("pi()"), "at character 3: unexpected '(' after the expression");
  EXPECT_EQ(error_of("1+"), "at character 3: unexpected end of text");
  EXPECT_EQ(error_of("2*)"), "at character 3: unexpected ')'");
  EXPECT_EQ(error_of("."), "at character 1: unexpected '.'");
  EXPECT_EQ(error_of("x # 2"), "at character 3: unexpected '#' after the expression");
  EXPECT_EQ(error_of("\xc3\xa9"), "at character 1: unexpected byte 0xc3");
  EXPECT_EQ(error_of("sin x"), "at character 5: expected '(' after 'sin'");
  EXPECT_EQ(error_of("atan2(1)"), "at character 1: 'atan2' takes 2 arguments, got 1");
  EXPECT_EQ(error_of("2*sin(1, 2)"), "at character 3: 'sin' takes 1 argument, got more");
  EXPECT_EQ(error_of("clamp(1, 2)"), "at character 1: 'clamp' takes 3 arguments, got 2");
  EXPECT_EQ(error_of("min(1,)"), "at character 7: unexpected ')'");
  EXPECT_EQ(error_of("1e"), "at character 2: exponent without digits");
  EXPECT_EQ(error_of("1e+x"), "at character 2: exponent without digits");
  EXPECT_EQ(error_of("x+1e400"), "at character 3: number out of range");
  EXPECT_EQ(error_of("1" + std::string(400, '0')), "at character 1: number out of range");
  EXPECT_EQ(error_of("1" + std::string(400, '0') + "e-90"), "at character 1: number out of range");
  EXPECT_EQ(error_of(std::string("x\0", 2)), "at character 2: control character (code 0)");
  EXPECT_EQ(error_of("1+\x01"), "at character 3: control character (code 1)");
  EXPECT_EQ(error_of("1\x7f"), "at character 2: control character (code 127)");
}

TEST(Expression, Limits) {
  // Length: 4096 characters parse, 4097 do not.
  const std::string sum = "1" + repeat("+1", 2047);
  ASSERT_EQ(sum.size(), 4095u);
  EXPECT_EQ(ev(sum + " "), 2048.0);
  EXPECT_EQ(error_of(sum + "  "), "at character 4097: expression longer than 4096 characters");
  // Nesting: 64 levels parse, 65 do not, whether parentheses, calls, signs or exponents.
  EXPECT_EQ(ev(repeat("(", 64) + "x" + repeat(")", 64), 5), 5.0);
  EXPECT_EQ(error_of(repeat("(", 65) + "x" + repeat(")", 65)),
            "at character 65: nesting deeper than 64 levels");
  EXPECT_EQ(ev(repeat("abs(", 64) + "x" + repeat(")", 64), -5), 5.0);
  EXPECT_EQ(error_of(repeat("abs(", 65) + "x" + repeat(")", 65)),
            "at character 257: nesting deeper than 64 levels");
  EXPECT_EQ(ev(repeat("-", 64) + "x", 5), 5.0);
  EXPECT_EQ(error_of(repeat("-", 65) + "x"), "at character 65: nesting deeper than 64 levels");
  EXPECT_EQ(ev("1" + repeat("^1", 64)), 1.0);
  EXPECT_EQ(error_of("1" + repeat("^1", 65)), "at character 130: nesting deeper than 64 levels");
  // Unbounded input is refused without deep recursion.
  EXPECT_NE(error_of(repeat("(", 4096)), "");
  // The deepest stack the nesting allows: four waiting values per level.
  const std::string deep = repeat("x+x*clamp(x,x,", 64) + "x+x*x" + repeat(")", 64);
  EXPECT_EQ(ev(deep, 0.5), 0.75);
}

TEST(Expression, RandomStringsOnlyParseOrThrowInputError) {
  std::mt19937 rng(27);
  const auto pick = [&](int n) { return int(std::uniform_int_distribution<int>(0, n - 1)(rng)); };
  // Valid expressions from the grammar, then mutated character by character.
  const char* atoms[] = {"x", "y", "z", "t", "pi", "e", "0", "1.5", ".5", "2.", "1e-3", "3E+2"};
  const char* f1[] = {"sin", "cos", "tan",  "asin", "acos",  "atan",
                      "exp", "log", "sqrt", "abs",  "floor", "ceil"};
  const char* f2[] = {"atan2", "min", "max", "pow"};
  const char* ops[] = {"+", "-", "*", "/", "^", " + ", " ^ "};
  std::function<std::string(int)> gen = [&](int d) -> std::string {
    switch (d > 0 ? pick(6) : 0) {
      case 0:
        return atoms[pick(12)];
      case 1:
        return gen(d - 1) + ops[pick(7)] + gen(d - 1);
      case 2:
        return "-" + gen(d - 1);
      case 3:
        return "(" + gen(d - 1) + ")";
      case 4:
        return std::string(f1[pick(12)]) + "(" + gen(d - 1) + ")";
      default:
        return pick(4) == 0 ? "clamp(" + gen(d - 1) + "," + gen(d - 1) + "," + gen(d - 1) + ")"
                            : std::string(f2[pick(4)]) + "(" + gen(d - 1) + ", " + gen(d - 1) + ")";
    }
  };
  const std::string alphabet = "0123456789.eE+-*/^(), \txyztpisncoabqlrgfmh";
  int parsed = 0, refused = 0;
  for (int it = 0; it < 20000; ++it) {
    std::string s;
    if (pick(4) == 0) {  // a string over the alphabet, sometimes with any byte
      const int n = pick(10) == 0 ? 4000 + pick(200) : pick(40);
      for (int k = 0; k < n; ++k)
        s += pick(50) == 0 ? char(pick(256)) : alphabet[pick(int(alphabet.size()))];
    } else {
      s = gen(pick(7));
      if (s.size() <= Expression::kMaxLength) {
        EXPECT_NO_THROW(Expression::parse(s)) << s;
      }
      for (int m = pick(4); m > 0 && !s.empty(); --m) {
        const std::size_t at = std::size_t(pick(int(s.size())));
        switch (pick(3)) {
          case 0:
            s.erase(at, 1);
            break;
          case 1:
            s.insert(at, 1, alphabet[pick(int(alphabet.size()))]);
            break;
          default:
            s[at] = char(pick(256));
            break;
        }
      }
    }
    try {
      const Expression e = Expression::parse(s);
      (void)e.eval(0.25, -0.5, 1.0, 2.0);
      ++parsed;
    } catch (const InputError& err) {
      EXPECT_EQ(std::string(err.what()).rfind("at character ", 0), 0u) << err.what();
      ++refused;
    } catch (...) {
      ADD_FAILURE() << "not an InputError: " << s;
    }
  }
  std::printf("random strings: %d parsed, %d refused\n", parsed, refused);
  EXPECT_GT(parsed, 2000);
  EXPECT_GT(refused, 2000);
}
