// CG on a borrowed CSR matrix, with the Jacobi preconditioner M = diag(A) (Saad, "Iterative
// Methods for Sparse Linear Systems", 2nd ed., sec. 10.2). The iteration itself is pcg().
#include <cmath>
#include <string>
#include <vector>

#include "core/errors.h"
#include "core/parallel.h"
#include "linalg/cg.h"

namespace kinema {

namespace {

std::string str(Index i) { return std::to_string(i); }

// Square, row_ptr monotone from 0, column indices in range: spmv must never read out of bounds.
void check_csr(const CsrView& A) {
  if (A.rows != A.cols)
    throw InvalidArgument("A: expected a square matrix, got " + str(A.rows) + " x " + str(A.cols));
  if (A.rows <= 0) throw InvalidArgument("A: expected a non-empty matrix, got 0 x 0");
  if (!A.row_ptr || A.row_ptr[0] != 0)
    throw InvalidArgument("A: row_ptr must start with 0");
  for (Index i = 0; i < A.rows; ++i)
    if (A.row_ptr[i + 1] < A.row_ptr[i])
      throw InvalidArgument("A: row_ptr must be non-decreasing, but row_ptr[" + str(i + 1) +
                            "] = " + str(A.row_ptr[i + 1]) + " < row_ptr[" + str(i) +
                            "] = " + str(A.row_ptr[i]));
  const Index nnz = A.row_ptr[A.rows];
  if (nnz > 0 && (!A.col_index || !A.values))
    throw InvalidArgument("A: col_index or values is null for " + str(nnz) + " entries");
  for (Index p = 0; p < nnz; ++p)
    if (A.col_index[p] < 0 || A.col_index[p] >= A.cols)
      throw InvalidArgument("A: column index " + str(A.col_index[p]) + " at position " + str(p) +
                            " is outside [0, " + str(A.cols) + ")");
}

// 1 / a_ii, summing duplicate diagonal entries as spmv does.
std::vector<Scalar> inverse_diagonal(const CsrView& A) {
  std::vector<Scalar> inv(static_cast<size_t>(A.rows));
  for (Index i = 0; i < A.rows; ++i) {
    Scalar d = 0;
    for (Index p = A.row_ptr[i]; p < A.row_ptr[i + 1]; ++p)
      if (A.col_index[p] == i) d += A.values[p];
    if (!(d > 0) || !std::isfinite(d))
      throw InvalidArgument("A: diagonal entry A[" + str(i) + ", " + str(i) + "] = " +
                            std::to_string(d) +
                            " is not positive; a symmetric positive definite matrix has a "
                            "positive diagonal (Jacobi preconditioning divides by it)");
    inv[static_cast<size_t>(i)] = 1 / d;
  }
  return inv;
}

}  // namespace

SolveInfo cg_csr(const CsrView& A, const Scalar* b, Scalar* x, bool jacobi,
                 const IterativeOptions& options, Interrupt& interrupt) {
  check_csr(A);
  const LinearOperator apply = [&A](const Scalar* v, Scalar* y) { spmv(A, v, y); };
  LinearOperator precond;
  std::vector<Scalar> inv_diag;
  if (jacobi) {
    inv_diag = inverse_diagonal(A);
    precond = [&inv_diag, n = A.rows](const Scalar* r, Scalar* z) {
      parallel_for(n, [&](Index i) { z[i] = inv_diag[static_cast<size_t>(i)] * r[i]; });
    };
  }
  return pcg(A.rows, apply, precond, b, x, options, interrupt);
}

}  // namespace kinema
