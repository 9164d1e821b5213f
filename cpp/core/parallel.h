// OpenMP helpers. Reductions are deterministic: the index range is cut into fixed blocks
// whose partial sums are added in block order, so a result is bitwise identical run to run
// and for any thread count (OpenMP's reduction clause promises neither).
#pragma once

#include <omp.h>

#include <algorithm>
#include <vector>

#include "core/types.h"

namespace kinema {

inline int num_threads() { return omp_get_max_threads(); }
inline void set_num_threads(int n) { omp_set_num_threads(n); }

// Below this many items a loop is not worth waking the thread team for.
constexpr Index kParallelGrain = 4096;
constexpr Index kReduceBlock = 4096;

// sum over i in [0, n) of term(i), reproducibly.
template <class Term>
Scalar parallel_sum(Index n, Term&& term) {
  if (n <= kReduceBlock) {
    Scalar s = 0;
    for (Index i = 0; i < n; ++i) s += term(i);
    return s;
  }
  const Index blocks = (n + kReduceBlock - 1) / kReduceBlock;
  std::vector<Scalar> partial(static_cast<size_t>(blocks));
#pragma omp parallel for schedule(static)
  for (Index b = 0; b < blocks; ++b) {
    const Index end = std::min(n, (b + 1) * kReduceBlock);
    Scalar s = 0;
    for (Index i = b * kReduceBlock; i < end; ++i) s += term(i);
    partial[static_cast<size_t>(b)] = s;
  }
  Scalar s = 0;
  for (Scalar p : partial) s += p;
  return s;
}

// for i in [0, n): body(i), in parallel when n is large enough.
template <class Body>
void parallel_for(Index n, Body&& body) {
#pragma omp parallel for schedule(static) if (n > kParallelGrain)
  for (Index i = 0; i < n; ++i) body(i);
}

}  // namespace kinema
