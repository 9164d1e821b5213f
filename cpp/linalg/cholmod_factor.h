// RAII wrapper around CHOLMOD's supernodal Cholesky factorisation A = L L^T (long-index
// interface, cholmod_l_*). Analysis (fill-reducing ordering, supernode detection) is done once;
// refactor() reuses it for a matrix of the same pattern, as Newton iterations need.
// Davis & Hager, "Dynamic supernodes in sparse Cholesky update/downdate", ACM TOMS 35 (2009).
#pragma once

#include <memory>

#include "core/types.h"

namespace kinema {

// A borrowed compressed-sparse-column matrix (or, equivalently for a symmetric matrix, CSR).
// Only the lower triangle is read, so the full symmetric matrix may be passed.
struct CscView {
  Index rows = 0;
  Index cols = 0;
  const Index* col_ptr = nullptr;   // cols + 1 entries
  const Index* row_index = nullptr; // col_ptr[cols] entries, sorted within each column
  const Scalar* values = nullptr;
};

class CholmodFactor {
 public:
  // Analyses and factorises A. Throws NotPositiveDefinite (with the failing column) or
  // InvalidArgument for a non-square or malformed matrix.
  explicit CholmodFactor(const CscView& A);
  ~CholmodFactor();
  CholmodFactor(const CholmodFactor&) = delete;
  CholmodFactor& operator=(const CholmodFactor&) = delete;
  CholmodFactor(CholmodFactor&&) noexcept;
  CholmodFactor& operator=(CholmodFactor&&) noexcept;

  // Re-factorises a matrix with the same sparsity pattern, reusing the symbolic analysis.
  void refactor(const CscView& A);

  // Solves A X = B for nrhs right-hand sides stored column by column (column-major, n x nrhs).
  void solve(const Scalar* b, Scalar* x, Index nrhs = 1) const;

  Index size() const;
  Index factor_nonzeros() const;  // nonzeros in L
  bool is_supernodal() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace kinema
