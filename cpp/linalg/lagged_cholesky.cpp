#include "linalg/lagged_cholesky.h"

#include "core/errors.h"
#include "core/timer.h"

namespace kinema {

bool LaggedCholesky::solve(const CsrView& A, const Scalar* b, Scalar* x, bool reuse, Scalar tol,
                           Index max_pcg, LaggedSolveStats& stats) {
  const Index n = A.rows;
  Stopwatch phase;
  if (reuse && has_factor() && !refactor_next_) {
    const LinearOperator op = [&](const Scalar* v, Scalar* y) { spmv(A, v, y); };
    const LinearOperator pre = [&](const Scalar* r, Scalar* z) { factor_->solve(r, z, 1); };
    Interrupt none;
    bool converged = false;
    try {
      const SolveInfo info =
          pcg(n, op, pre, b, x, IterativeOptions{tol, max_pcg}, none, {}, &workspace_);
      stats.pcg_iterations += info.iterations;
      converged = info.converged;
      refactor_next_ = info.iterations > max_pcg / 2;
    } catch (const InvalidArgument&) {
      // pcg's only InvalidArgument: p^T A p <= 0, A is not positive definite. The
      // factorisation below tells for sure and names it.
      stats.pcg_iterations += max_pcg;
    }
    stats.seconds_solve += phase.seconds();
    if (converged) return true;
    phase.restart();
  }
  const CscView C{n, n, A.row_ptr, A.col_index, A.values};
  ++stats.factorizations;
  refactor_next_ = false;
  try {
    if (!factor_) factor_ = std::make_unique<CholmodFactor>(C);
    else factor_->refactor(C);
  } catch (const NotPositiveDefinite&) {
    valid_ = false;
    stats.seconds_factor += phase.seconds();
    return false;
  }
  valid_ = true;
  stats.seconds_factor += phase.seconds();
  phase.restart();
  factor_->solve(b, x, 1);
  stats.seconds_solve += phase.seconds();
  return true;
}

}  // namespace kinema
