// Storage for the large work vectors of kinema's solvers (multigrid levels, PCG vectors): on
// transparent huge pages where Linux offers them. Its default THP mode, "madvise", backs memory
// by 2 MiB pages only on request, as numpy requests them for its large arrays; kinema's grid
// kernels stream several planes at once, and on 4 KB pages they paid for the page walks (the
// 3D apply and sweep ran 4-16% slower on them in an interleaved A/B; bench/RESULTS.md, appendix A.1,
// "Huge pages"). Blocks below kHugeThreshold come from operator new as usual.
#pragma once

#include <cstddef>
#include <cstdlib>
#include <new>
#include <vector>

#if defined(__linux__)
#include <sys/mman.h>
#endif

#include "core/types.h"

namespace kinema {

template <class T>
struct HugePageAllocator {
  using value_type = T;
  static constexpr std::size_t kHugeThreshold = std::size_t{4} << 20;  // as numpy's
  static constexpr std::size_t kHugePage = std::size_t{2} << 20;

  HugePageAllocator() = default;
  template <class U>
  HugePageAllocator(const HugePageAllocator<U>&) noexcept {}

  T* allocate(std::size_t n) {
    const std::size_t bytes = n * sizeof(T);
#if defined(__linux__)
    if (bytes >= kHugeThreshold) {
      void* p = nullptr;
      if (posix_memalign(&p, kHugePage, bytes) != 0) throw std::bad_alloc();
      // Advice only: where THP is off the kernel says no and the pages stay 4 KB.
      madvise(p, bytes, MADV_HUGEPAGE);
      return static_cast<T*>(p);
    }
#endif
    return static_cast<T*>(::operator new(bytes));
  }

  void deallocate(T* p, std::size_t n) noexcept {
#if defined(__linux__)
    if (n * sizeof(T) >= kHugeThreshold) {
      std::free(p);
      return;
    }
#endif
    ::operator delete(p);
  }

  template <class U>
  bool operator==(const HugePageAllocator<U>&) const noexcept { return true; }
  template <class U>
  bool operator!=(const HugePageAllocator<U>&) const noexcept { return false; }
};

using ScalarBuffer = std::vector<Scalar, HugePageAllocator<Scalar>>;

}  // namespace kinema
