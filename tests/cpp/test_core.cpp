// Core helpers: the deterministic reduction is exact on integers and independent of the
// thread count; the interrupt poll is honoured.
#include <gtest/gtest.h>

#include <vector>

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
