// 64-bit FNV-1a hash of a byte range: checkpoint checksums and scene fingerprints.
#pragma once

#include <cstddef>
#include <cstdint>

namespace amalgam {

inline std::uint64_t fnv1a64(const void* data, std::size_t n,
                             std::uint64_t h = 0xcbf29ce484222325ULL) {
  const unsigned char* p = static_cast<const unsigned char*>(data);
  for (std::size_t i = 0; i < n; ++i) {
    h ^= p[i];
    h *= 0x100000001b3ULL;
  }
  return h;
}

// fnv1a64 of one byte range from two starting values at once: h1 and h2 become what
// fnv1a64(data, n, h1) and fnv1a64(data, n, h2) return. Each byte's multiply waits for the
// previous one's, so the two independent chains in one loop take about the time of one.
inline void fnv1a64_pair(const void* data, std::size_t n, std::uint64_t& h1, std::uint64_t& h2) {
  const unsigned char* p = static_cast<const unsigned char*>(data);
  std::uint64_t a = h1, b = h2;
  for (std::size_t i = 0; i < n; ++i) {
    a ^= p[i];
    b ^= p[i];
    a *= 0x100000001b3ULL;
    b *= 0x100000001b3ULL;
  }
  h1 = a;
  h2 = b;
}

}  // namespace amalgam
