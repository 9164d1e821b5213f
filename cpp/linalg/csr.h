// Sparse matrix-vector products on borrowed CSR storage, OpenMP over rows.
#pragma once

#include "core/types.h"

namespace kinema {

// A borrowed compressed-sparse-row matrix with 64-bit indices (scipy's CSR arrays, zero-copy).
struct CsrView {
  Index rows = 0;
  Index cols = 0;
  const Index* row_ptr = nullptr;   // rows + 1 entries
  const Index* col_index = nullptr; // row_ptr[rows] entries
  const Scalar* values = nullptr;
};

// y = A x
void spmv(const CsrView& A, const Scalar* x, Scalar* y);

}  // namespace kinema
