#include "linalg/csr.h"

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

}  // namespace kinema
