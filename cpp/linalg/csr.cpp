#include "linalg/csr.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include "core/parallel.h"

namespace kinema {

// Each row's dot product runs serially in storage order, so y is bitwise identical for any
// thread count; the static schedule gives each thread a contiguous block of rows.
void spmv(const CsrView& A, const Scalar* x, Scalar* y) {
  const Index* row_ptr = A.row_ptr;
  const Index* col = A.col_index;
  const Scalar* val = A.values;
#pragma omp parallel for schedule(static) if (A.rows > kParallelGrain)
  for (Index i = 0; i < A.rows; ++i) {
    Scalar s = 0;
    for (Index p = row_ptr[i]; p < row_ptr[i + 1]; ++p) s += val[p] * x[col[p]];
    y[i] = s;
  }
}

namespace {

template <class I>
Asymmetry asymmetry_of(const BasicCsrView<I>& A) {
  const I* row_ptr = A.row_ptr;
  const I* col = A.col_index;
  const Scalar* val = A.values;
  auto transposed = [&](Index i, Index j) -> Scalar {  // a_ji; 0 if j is out of range
    if (j < 0 || j >= A.rows) return 0;
    const I* first = col + row_ptr[j];
    const I* last = col + row_ptr[j + 1];
    const I* hit = std::lower_bound(first, last, static_cast<I>(i));
    return (hit != last && *hit == i) ? val[hit - col] : 0.0;
  };
  // Per-row maxima, then a serial scan: the reported location is the first largest one.
  std::vector<Scalar> worst(A.rows, 0);
  std::vector<Index> where(A.rows, -1);
#pragma omp parallel for schedule(static) if (A.rows > kParallelGrain)
  for (Index i = 0; i < A.rows; ++i)
    for (Index p = row_ptr[i]; p < row_ptr[i + 1]; ++p) {
      const Scalar d = std::abs(val[p] - transposed(i, col[p]));
      if (d > worst[i]) {
        worst[i] = d;
        where[i] = col[p];
      }
    }
  Asymmetry result;
  for (Index i = 0; i < A.rows; ++i)
    if (worst[i] > result.value) result = {worst[i], i, where[i]};
  return result;
}

}  // namespace

Asymmetry asymmetry(const CsrView& A) { return asymmetry_of(A); }
Asymmetry asymmetry(const CsrView32& A) { return asymmetry_of(A); }

}  // namespace kinema
