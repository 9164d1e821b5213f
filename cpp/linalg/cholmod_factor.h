// RAII wrapper around CHOLMOD's supernodal Cholesky factorisation P A P^T = L L^T (through
// CHOLMOD's int interface when the matrix and its factor fit in int, else cholmod_l_*). Analysis (fill-reducing ordering P, supernode detection) is done once;
// refactor() reuses it for a matrix of the same pattern, as Newton iterations need.
// Chen, Davis, Hager & Rajamanickam, "CHOLMOD, supernodal sparse Cholesky factorization and
// update/downdate", ACM TOMS 35 (2008).
//
// Thread safety: one factor may be used from several threads; its calls are serialised (CHOLMOD
// keeps its workspace in the factor's cholmod_common). Different factors run independently.
// CHOLMOD's dense kernels run in the BLAS (OpenBLAS), with the BLAS's own threads.
#pragma once

#include <cstdint>
#include <memory>

#include "core/types.h"

namespace kinema {

// A borrowed compressed-sparse-column matrix (or, equivalently for a symmetric matrix, CSR)
// with indices of type I: kinema's 64-bit Index (CscView) or scipy's default 32 bits
// (CscView32, read without conversion). Only the lower triangle is read, so the full symmetric
// matrix may be passed.
template <class I>
struct BasicCscView {
  Index rows = 0;
  Index cols = 0;
  const I* col_ptr = nullptr;   // cols + 1 entries
  const I* row_index = nullptr; // col_ptr[cols] entries, sorted within each column
  const Scalar* values = nullptr;
};
using CscView = BasicCscView<Index>;
using CscView32 = BasicCscView<std::int32_t>;

// Fill-reducing ordering chosen by the analysis.
enum class CholmodOrdering {
  Default,  // CHOLMOD's choice: AMD, and METIS/NESDIS when AMD's fill is poor
  Amd,      // approximate minimum degree only
  Natural,  // no permutation: a failing column is then the first non-positive leading minor
  Metis,    // METIS nested dissection only (less fill on large 2D/3D grid problems)
};

// Index width of the CHOLMOD interface. Auto: int whenever the matrix and its factor fit in it
// (less memory traffic in the analysis and the supernodal assembly), else long.
enum class CholmodIndexWidth { Auto, Int, Long };

class CholmodFactor {
 public:
  // Analyses and factorises A. Throws NotPositiveDefinite (with the failing column) or
  // InvalidArgument for a non-square or malformed matrix (unsorted or duplicate row indices
  // included) or non-finite values. The view is only read during the call (no reference kept).
  // Index width Int throws InvalidArgument when the matrix or its factor does not fit in int.
  explicit CholmodFactor(const CscView& A, CholmodOrdering ordering = CholmodOrdering::Default,
                         CholmodIndexWidth width = CholmodIndexWidth::Auto);
  explicit CholmodFactor(const CscView32& A, CholmodOrdering ordering = CholmodOrdering::Default,
                         CholmodIndexWidth width = CholmodIndexWidth::Auto);
  ~CholmodFactor();
  CholmodFactor(const CholmodFactor&) = delete;
  CholmodFactor& operator=(const CholmodFactor&) = delete;
  CholmodFactor(CholmodFactor&&) noexcept;
  CholmodFactor& operator=(CholmodFactor&&) noexcept;

  // Re-factorises a matrix with the same sparsity pattern, reusing the symbolic analysis.
  // Throws InvalidArgument when the pattern differs, NotPositiveDefinite when a pivot fails
  // (the factor is then unusable until a successful refactor).
  void refactor(const CscView& A);
  void refactor(const CscView32& A);

  // Solves A X = B for nrhs right-hand sides stored column by column (column-major, n x nrhs).
  // b and x may not overlap.
  void solve(const Scalar* b, Scalar* x, Index nrhs = 1) const;

  Index size() const;
  Index factor_nonzeros() const;  // nonzeros in L
  bool is_supernodal() const;
  int index_bits() const;  // 32 (CHOLMOD's int interface) or 64 (cholmod_l_*)
  // log det A = 2 sum_j log L_jj.
  Scalar log_determinant() const;
  // The fill-reducing permutation: row/column perm[k] of A is row/column k of P A P^T.
  const Index* permutation() const;

  struct Impl;  // the factorisation in CHOLMOD's int or long interface (see the .cpp)

 private:
  std::unique_ptr<Impl> impl_;
};

}  // namespace kinema
