// OpenMP helpers. Reductions are deterministic: the index range is cut into fixed blocks
// whose partial sums are added in block order, so a result is bitwise identical run to run
// and for any thread count (OpenMP's reduction clause promises neither).
#pragma once

#include <omp.h>

#include <algorithm>
#include <atomic>
#include <vector>

#include "core/types.h"

namespace kinema {

// The number of threads a parallel region started on the calling thread will use.
inline int num_threads() { return omp_get_max_threads(); }

// kinema's thread count (km.set_num_threads) is one setting for the whole process, whereas
// OpenMP's omp_set_num_threads only changes the calling thread's count (a Python worker thread
// would keep the default). The setting lives here, 0 meaning OpenMP's default; the bindings
// apply it to the calling thread on entry to every long call (use_thread_count_setting).
inline std::atomic<int>& thread_count_setting() {
  static std::atomic<int> count{0};
  return count;
}

// Far more threads than cores only adds overhead, and OpenMP aborts when it cannot create them.
inline int max_thread_count() { return std::max(64, 4 * omp_get_num_procs()); }

inline void set_num_threads(int n) {
  thread_count_setting() = n;
  omp_set_num_threads(n);
}

// The process-wide count, or OpenMP's default when none was set.
inline int configured_num_threads() {
  const int n = thread_count_setting();
  return n > 0 ? n : omp_get_max_threads();
}

inline void use_thread_count_setting() {
  const int n = thread_count_setting();
  if (n > 0 && omp_get_max_threads() != n) omp_set_num_threads(n);
}

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
