// Core helpers: the deterministic reduction is exact on integers and independent of the
// thread count; the interrupt poll is honoured.
#include <gtest/gtest.h>

#include <cstdint>
#include <vector>

#include "core/buffer.h"
#include "core/interrupt.h"
#include "core/parallel.h"

namespace kinema {

TEST(ParallelSum, ExactOnIntegersAndThreadIndependent) {
  const Index n = 1'000'003;
  const int saved = num_threads();
  std::vector<Scalar> sums;
  for (int t : {1, 2, 3}) {
    set_num_threads(t);
    sums.push_back(parallel_sum(n, [](Index i) { return static_cast<Scalar>(i % 1000) * 1e-3; }));
  }
  set_num_threads(saved);
  // Bitwise equality across thread counts is the promise, not just closeness.
  EXPECT_EQ(sums[0], sums[1]);
  EXPECT_EQ(sums[0], sums[2]);
  EXPECT_EQ(parallel_sum(n, [](Index i) { return static_cast<Scalar>(i); }),
            static_cast<Scalar>(n) * (n - 1) / 2);
}

TEST(Interrupt, PollStopsTheComputation) {
  Interrupt interrupt([] { return true; }, 0.0);
  EXPECT_THROW(interrupt.check(), Interrupted);
  Interrupt never;
  EXPECT_NO_THROW(never.check());
}

}  // namespace kinema

namespace kinema {
namespace {

// Large ScalarBuffers sit on 2 MiB boundaries (so that the kernel can back them by huge pages)
// and small ones come from operator new; both hold and copy their values like any vector.
TEST(ScalarBuffer, LargeBlocksAreHugePageAlignedAndBehaveAsVectors) {
  for (std::size_t n : {std::size_t{10}, std::size_t{1} << 20}) {  // 80 B and 8 MiB
    ScalarBuffer v(n, 1.5);
    if (n * sizeof(Scalar) >= HugePageAllocator<Scalar>::kHugeThreshold) {
#if defined(__linux__)
      EXPECT_EQ(reinterpret_cast<std::uintptr_t>(v.data()) % HugePageAllocator<Scalar>::kHugePage, 0u);
#endif
    }
    v.back() = 2.5;
    ScalarBuffer w = v;
    w.resize(n + 3, 0.5);
    EXPECT_EQ(w[0], 1.5);
    EXPECT_EQ(w[n - 1], 2.5);
    EXPECT_EQ(w[n + 2], 0.5);
  }
}

}  // namespace
}  // namespace kinema
