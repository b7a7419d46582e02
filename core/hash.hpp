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

}  // namespace amalgam
