// ExactSum: the exact sum of doubles, whatever the order they are added in, rounded once at the
// end. A fixed-point superaccumulator (Kulisch's long accumulator, in the "small
// superaccumulator" form of R. M. Neal, "Fast exact summation using small and large
// superaccumulators", arXiv:1505.05571, 2015): every finite double is m·2^e with an integer
// m < 2^53 and e in [-1074, 971], so it is a sum of at most three 32-bit digits of a base-2^32
// number whose lowest digit weighs 2^-1074. Each digit is kept in an int64 with 31 bits of headroom
// for carries, propagated only every 2^30 additions and before reading.
//
// What it is for: diagnostics summed over particles that live on different ranks, threads or
// chunks (kinetic energy, momentum, mass). Integer digit sums are associative, so the ranks' or
// chunks' accumulators merge in any order (an MPI_SUM over `words()`, for one) and the value is
// the same to the last bit on every rank count, backend and thread count, and correctly rounded
// (to nearest, ties to even) except in the subnormal range, where it may be one ulp off but is
// still a function of the exact sum only.
//
// Non-finite terms: a NaN anywhere, or both +inf and -inf, give NaN; otherwise an infinite term
// gives that infinity. A finite sum beyond the double range gives ±inf.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <vector>

namespace amalgam {

class ExactSum {
 public:
  // Digits cover 2^-1074 .. 2^(32·kDigits - 1074 - 1): the largest double's top bit (2^1023) sits
  // in digit 65, the three above absorb the carries of up to 2^64 terms.
  static constexpr int kDigits = 68;
  // words(): the digits, then the counts of NaN, +inf and -inf terms.
  static constexpr int kWords = kDigits + 3;

  void add(double x) {
    std::uint64_t b;
    std::memcpy(&b, &x, sizeof b);
    const int field = int((b >> 52) & 0x7ff);
    std::uint64_t m = b & ((std::uint64_t(1) << 52) - 1);
    if (field == 0x7ff) {  // inf or NaN
      ++word_[kDigits + (m ? 0 : (b >> 63) ? 2 : 1)];
      return;
    }
    if (field == 0 && m == 0) return;  // ±0
    int e = -1074;                     // subnormal: m·2^-1074
    if (field) m |= std::uint64_t(1) << 52, e = field - 1075;
    const int pos = e + 1074, k = pos >> 5, s = pos & 31;
    // m·2^s < 2^85: three digits (the low 32 bits of m << s are exact even where it wraps).
    const std::uint64_t lo = (m << s) & 0xffffffffu, mid = (m >> (32 - s)) & 0xffffffffu;
    const std::uint64_t hi = s ? (m >> (64 - s)) : 0;  // a shift by 64 would be undefined
    if (b >> 63) {
      word_[k] -= std::int64_t(lo);
      word_[k + 1] -= std::int64_t(mid);
      word_[k + 2] -= std::int64_t(hi);
    } else {
      word_[k] += std::int64_t(lo);
      word_[k + 1] += std::int64_t(mid);
      word_[k + 2] += std::int64_t(hi);
    }
    if (++pending_ == kCarryEvery) carry();
  }

  ExactSum& operator+=(double x) {
    add(x);
    return *this;
  }

  // Adds another accumulator's exact sum (both carried first, so no digit can overflow).
  void merge(const ExactSum& o) {
    ExactSum c = o;
    c.carry();
    carry();
    for (int i = 0; i < kWords; ++i) word_[i] += c.word_[i];
    pending_ = 2;  // every digit below the top is now < 2^33 in magnitude
  }

  // The digits carried to [0, 2^32) (the top one signed) and the non-finite counts: what ranks
  // sum word by word (an exact, order-independent integer reduction) before `from_words`.
  std::vector<std::int64_t> words() const {
    ExactSum c = *this;
    c.carry();
    return std::vector<std::int64_t>(c.word_, c.word_ + kWords);
  }
  // The sum of accumulators whose words() were added word by word (at most 2^30 of them).
  static ExactSum from_words(const std::vector<std::int64_t>& w) {
    ExactSum s;
    for (int i = 0; i < kWords && i < int(w.size()); ++i) s.word_[i] = w[std::size_t(i)];
    s.pending_ = kCarryEvery - 1;
    s.carry();
    return s;
  }

  // The exact sum rounded to the nearest double.
  double value() const {
    const std::int64_t nan = word_[kDigits], pinf = word_[kDigits + 1], ninf = word_[kDigits + 2];
    if (nan || (pinf && ninf)) return std::numeric_limits<double>::quiet_NaN();
    if (pinf) return std::numeric_limits<double>::infinity();
    if (ninf) return -std::numeric_limits<double>::infinity();
    ExactSum c = *this;
    c.carry();
    const bool negative = c.word_[kDigits - 1] < 0;
    if (negative) {  // magnitude: negate every digit, then carry again
      for (int i = 0; i < kDigits; ++i) c.word_[i] = -c.word_[i];
      c.carry();
    }
    int h = kDigits - 1;
    while (h >= 0 && c.word_[h] == 0) --h;
    if (h < 0) return 0.0;
    // The top 64 bits of the magnitude, its lowest bit or-ed with every bit below them (a sticky
    // bit: with 11 bits below the double's 53, that makes the one conversion round correctly).
    const std::uint64_t d2 = std::uint64_t(c.word_[h]);
    const std::uint64_t d1 = h >= 1 ? std::uint64_t(c.word_[h - 1]) : 0;
    const std::uint64_t d0 = h >= 2 ? std::uint64_t(c.word_[h - 2]) : 0;
    const int shift = __builtin_clzll(d2) - 32;  // so that d2's top bit becomes bit 95 of `top`
    unsigned __int128 top = (static_cast<unsigned __int128>(d2) << 64) |
                            (static_cast<unsigned __int128>(d1) << 32) | d0;
    top <<= shift;
    std::uint64_t mant = std::uint64_t(top >> 32);  // bits 95..32
    bool sticky = std::uint64_t(top) & 0xffffffffu;
    for (int i = h - 3; i >= 0 && !sticky; --i) sticky = c.word_[i] != 0;
    if (sticky) mant |= 1;
    // Bit j of the unshifted d2:d1:d0 weighs 2^(32·(h - 2) - 1074 + j); mant's lowest bit is bit
    // 32 - shift of it.
    const int exp = 32 * (h - 2) - 1074 + 32 - shift;
    const double r = std::ldexp(double(mant), exp);
    return negative ? -r : r;
  }

 private:
  static constexpr int kCarryEvery = 1 << 30;

  // Digits to [0, 2^32) from the lowest up (an arithmetic shift is a floor division); the top
  // digit keeps the sign.
  void carry() {
    std::int64_t c = 0;
    for (int i = 0; i < kDigits - 1; ++i) {
      const std::int64_t d = word_[i] + c;
      c = d >> 32;                  // floor(d / 2^32)
      word_[i] = d & 0xffffffffLL;  // d - c·2^32
    }
    word_[kDigits - 1] += c;
    pending_ = 0;
  }

  std::int64_t word_[kWords] = {};
  std::int64_t pending_ = 0;
};

}  // namespace amalgam
