// Solves a sequence of symmetric positive definite systems A_k x = b_k of one sparsity pattern
// whose values drift slowly (Newton iterations, implicit time steps), reusing Cholesky factors:
//   x = PCG(A_k, b_k, preconditioner (L_j L_j^T)^-1)  with L_j the factor of an earlier A_j,
// refactorising A_k itself (and solving directly) only when PCG does not reach the tolerance
// within `max_pcg` iterations, or needed more than max_pcg / 2
// iterations on the previous solve (the matrix has drifted: refactorise before wasting a try).
// A factorisation costs tens of PCG iterations on 2D/3D elasticity meshes, and a lagged factor
// typically converges in a few, which is the whole saving (the preconditioner lagging of
// Knoll & Keyes, "Jacobian-free Newton-Krylov methods", J. Comput. Phys. 193, 2004). The
// symbolic analysis is done once.
// Decisions depend on iteration counts only, never on timings, so runs are deterministic.
#pragma once

#include <memory>

#include "core/types.h"
#include "linalg/cg.h"
#include "linalg/cholmod_factor.h"
#include "linalg/csr.h"

namespace kinema {

struct LaggedSolveStats {
  Index pcg_iterations = 0;
  Index factorizations = 0;
  double seconds_factor = 0, seconds_solve = 0;
};

class LaggedCholesky {
 public:
  // reuse = false: refactorise every call (a plain direct solve with the analysis reused).
  // x holds PCG's initial guess on entry (a direct solve ignores it).
  // tol: relative residual ||b - A x|| / ||b|| required of a PCG solution; max_pcg: its cap.
  // Returns false when A is not positive definite: found by PCG (negative curvature; the
  // lagged factor is kept) or by the factorisation (the factor is then invalid until the next
  // successful one). A is the full symmetric
  // matrix in CSR form (its own CSC).
  bool solve(const CsrView& A, const Scalar* b, Scalar* x, bool reuse, Scalar tol, Index max_pcg,
             LaggedSolveStats& stats);

  bool has_factor() const { return factor_ && valid_; }
  // The next reuse = true solve refactorises first (PCG needed many iterations last time).
  bool refactor_pending() const { return refactor_next_; }

  // x = L^-T L^-1 b with the current factor (requires has_factor()): the exact solve of the
  // matrix last factorised.
  void solve_with_factor(const Scalar* b, Scalar* x) const;

 private:
  std::unique_ptr<CholmodFactor> factor_;
  bool valid_ = false;
  bool refactor_next_ = false;
  CgWorkspace workspace_;
};

}  // namespace kinema
