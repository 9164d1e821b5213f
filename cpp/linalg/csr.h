// Sparse matrix-vector products on borrowed CSR storage, OpenMP over rows.
#pragma once

#include <cstdint>

#include "core/types.h"

namespace kinema {

// A borrowed compressed-sparse-row matrix (scipy's CSR arrays, zero-copy) with indices of type
// I: kinema's 64-bit Index (CsrView), or scipy's default 32 bits (CsrView32).
template <class I>
struct BasicCsrView {
  Index rows = 0;
  Index cols = 0;
  const I* row_ptr = nullptr;   // rows + 1 entries
  const I* col_index = nullptr; // row_ptr[rows] entries
  const Scalar* values = nullptr;
};
using CsrView = BasicCsrView<Index>;
using CsrView32 = BasicCsrView<std::int32_t>;

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
Asymmetry asymmetry(const CsrView32& A);

}  // namespace kinema
