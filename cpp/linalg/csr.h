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

// The largest |a_ij - a_ji| of a square CSR matrix with sorted column indices, and where it
// occurs (a missing transposed entry counts as zero). Binary search of each transposed entry,
// in parallel over rows: O(nnz log(row length)), no transpose built.
struct Asymmetry {
  Scalar value = 0;
  Index row = -1, col = -1;
};
Asymmetry asymmetry(const CsrView& A);

}  // namespace kinema
