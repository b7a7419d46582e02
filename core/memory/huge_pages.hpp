// Transparent huge pages for the particle set's large arrays. On Linux with the kernel's THP
// setting "madvise" (Debian's default), anonymous memory gets 4 KiB pages unless the program asks
// for huge ones, and first touching a large array costs one page fault per 4 KiB: on the
// development VM that made setting up 10^6 particles take 0.76 s instead of 0.08 s, and the first
// frame-start snapshot 0.41 s instead of 0.19 (docs/benchmarks.md, "The grid update in vectors of
// nodes, ..."). The allocator below asks for huge pages (madvise MADV_HUGEPAGE) on every
// allocation of at least 4 MiB, before anything touches it; the kernel may still decline.
// Elsewhere (other systems, THP "never") it is the standard allocator.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <vector>

#if defined(__linux__)
#include <sys/mman.h>
#endif

namespace amalgam {

// madvise(MADV_HUGEPAGE) over the whole 2 MiB pages inside [p, p + bytes); errors are ignored
// (a hint: the memory works either way).
inline void advise_huge_pages(void* p, std::size_t bytes) {
#if defined(__linux__) && defined(MADV_HUGEPAGE)
  constexpr std::uintptr_t kHuge = std::uintptr_t(1) << 21;
  const std::uintptr_t a = reinterpret_cast<std::uintptr_t>(p);
  const std::uintptr_t b = (a + kHuge - 1) & ~(kHuge - 1), e = (a + bytes) & ~(kHuge - 1);
  if (e > b) (void)madvise(reinterpret_cast<void*>(b), e - b, MADV_HUGEPAGE);
#else
  (void)p;
  (void)bytes;
#endif
}

template <class T>
struct HugePageAllocator {
  using value_type = T;
  static constexpr std::size_t kThreshold = std::size_t(4) << 20;  // bytes
  HugePageAllocator() = default;
  template <class U>
  HugePageAllocator(const HugePageAllocator<U>&) noexcept {}
  T* allocate(std::size_t n) {
    T* p = std::allocator<T>().allocate(n);
    if (n * sizeof(T) >= kThreshold) advise_huge_pages(p, n * sizeof(T));
    return p;
  }
  void deallocate(T* p, std::size_t n) noexcept { std::allocator<T>().deallocate(p, n); }
  template <class U>
  bool operator==(const HugePageAllocator<U>&) const noexcept {
    return true;
  }
  template <class U>
  bool operator!=(const HugePageAllocator<U>&) const noexcept {
    return false;
  }
};

template <class T>
using HugePageVector = std::vector<T, HugePageAllocator<T>>;

}  // namespace amalgam
