#include "linalg/spd_solver.h"

#include "core/timer.h"
#include "linalg/cg.h"

namespace kinema {

bool SpdSolver::solve(LinearSolver kind, const CsrView& A, const Scalar* b, Scalar* x, Scalar tol,
                      bool reuse, Interrupt& interrupt, SpdSolveStats& stats) {
  if (kind == LinearSolver::CG) {
    Stopwatch phase;
    const SolveInfo info = cg_csr(A, b, x, true, IterativeOptions{tol, 0}, interrupt);
    stats.cg_iterations += info.iterations;
    stats.converged = info.converged;
    stats.seconds_solve += phase.seconds();
    return true;
  }
  LaggedSolveStats s;
  const bool lagged = reuse && kind != LinearSolver::CholmodDirect;
  const bool ok = lagged_.solve(A, b, x, lagged, tol, 25, s);
  stats.cg_iterations += s.pcg_iterations;
  stats.factorizations += s.factorizations;
  stats.seconds_factor += s.seconds_factor;
  stats.seconds_solve += s.seconds_solve;
  stats.converged = ok;
  return ok;
}

bool SpdSolver::solve_exact(const CsrView& A, const Scalar* b, Scalar* x, bool factor_is_current,
                            SpdSolveStats& stats) {
  if (factor_is_current && lagged_.has_factor()) {
    Stopwatch phase;
    lagged_.solve_with_factor(b, x);
    stats.seconds_solve += phase.seconds();
    return true;
  }
  Interrupt none;  // a direct solve has no iterations to interrupt
  return solve(LinearSolver::CholmodDirect, A, b, x, 0, false, none, stats);
}

}  // namespace kinema
