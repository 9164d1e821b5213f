// The linear solver of the implicit mechanics steps (mass-spring, FEM, contact), chosen once
// here: a sequence of symmetric positive definite systems A_k x = b_k of one sparsity pattern.
//   Cholmod        PCG preconditioned by a lagged CHOLMOD factor (linalg/lagged_cholesky.h),
//                  refactorised when PCG stalls; the analysis is done once.
//   CholmodDirect  a fresh CHOLMOD factorisation every solve (analysis reused): exact.
//   CholmodPcg     the lagged factor; kept as a name of its own for callers that use a fixed
//                  PCG tolerance where Cholmod adapts it (FEM's inexact Newton).
//   CG             Jacobi-preconditioned CG, no factorisation.
// An adjoint solve (implicit function theorem) reuses the factor of the converged matrix:
// solve_exact() factorises A unless the current factor is already A's, then solves directly.
#pragma once

#include <vector>

#include "core/interrupt.h"
#include "core/types.h"
#include "linalg/csr.h"
#include "linalg/lagged_cholesky.h"

namespace kinema {

enum class LinearSolver { Cholmod, CholmodDirect, CholmodPcg, CG };

struct SpdSolveStats {
  Index cg_iterations = 0;
  Index factorizations = 0;
  double seconds_factor = 0, seconds_solve = 0;
  bool converged = true;  // CG reached tol (the CHOLMOD kinds always converge or fail)
};

class SpdSolver {
 public:
  // Solves A x = b to the relative residual tol (exact for CholmodDirect). x holds the initial
  // guess of PCG on entry. reuse = false forces a fresh factorisation for the CHOLMOD kinds.
  // Returns false when A was found not positive definite (by the factorisation or by PCG's
  // negative curvature); CG's non-convergence is reported in stats.converged instead.
  bool solve(LinearSolver kind, const CsrView& A, const Scalar* b, Scalar* x, Scalar tol,
             bool reuse, Interrupt& interrupt, SpdSolveStats& stats);

  // x = A^-1 b to rounding with a CHOLMOD factor of A. `factor_is_current` says the last
  // solve() with a CHOLMOD kind factorised exactly this A (its values unchanged since), so
  // the factor is reused. Returns false when A is not positive definite.
  bool solve_exact(const CsrView& A, const Scalar* b, Scalar* x, bool factor_is_current,
                   SpdSolveStats& stats);

  // The lagged factor's own history, for callers that record it in their State (bitwise resume).
  bool refactor_pending() const { return lagged_.refactor_pending(); }
  // A valid CHOLMOD factor is held (solve_exact with factor_is_current = true uses it).
  bool has_factor() const { return lagged_.has_factor(); }

 private:
  LaggedCholesky lagged_;
};

}  // namespace kinema
