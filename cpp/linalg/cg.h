// Preconditioned conjugate gradients (Hestenes & Stiefel 1952; Saad, "Iterative Methods for
// Sparse Linear Systems", 2nd ed., Alg. 9.1) for symmetric positive definite systems, written
// once over abstract operators so the sparse-matrix and matrix-free grid solvers share it.
#pragma once

#include <functional>
#include <vector>

#include "core/buffer.h"
#include "core/interrupt.h"
#include "core/types.h"
#include "linalg/csr.h"
#include "linalg/solve_info.h"

namespace kinema {

// y = op(x) for vectors of length n.
using LinearOperator = std::function<void(const Scalar* x, Scalar* y)>;

// The four work vectors of PCG; a solver that solves repeatedly keeps one to allocate nothing.
struct CgWorkspace {
  ScalarBuffer r, z, p, q;
};

// Solves A x = b by PCG. x holds the initial guess on entry. `precond` applies z = M^-1 r and
// may be empty (no preconditioning). `project` (optional) removes a null-space component from
// a vector in place, for singular consistent systems such as the pure-Neumann Laplacian.
SolveInfo pcg(Index n, const LinearOperator& A, const LinearOperator& precond, const Scalar* b,
              Scalar* x, const IterativeOptions& options, Interrupt& interrupt,
              const std::function<void(Scalar*)>& project = {}, CgWorkspace* workspace = nullptr);

// CG on a CSR matrix with optional Jacobi (diagonal) preconditioning.
SolveInfo cg_csr(const CsrView& A, const Scalar* b, Scalar* x, bool jacobi,
                 const IterativeOptions& options, Interrupt& interrupt);

}  // namespace kinema
