// Iterative solvers for the cell-centred Poisson operator A u = b (poisson_operator.h):
// weighted Jacobi, red-black Gauss-Seidel, Jacobi-preconditioned CG, multigrid V-cycles and
// multigrid-preconditioned CG (McAdams, Sifakis & Teran 2010). Built once per grid, boundary
// and solid mask; owns the multigrid hierarchy and scratch vectors, so repeated solves (one per
// time step) allocate nothing.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "core/interrupt.h"
#include "poisson/multigrid.h"
#include "poisson/poisson_operator.h"
#include "linalg/cg.h"
#include "linalg/solve_info.h"

namespace kinema {

enum class PoissonMethod { Jacobi, GaussSeidel, CG, Multigrid, MGPCG };

struct PoissonConfig {
  PoissonMethod method = PoissonMethod::MGPCG;
  Scalar jacobi_omega = 0.8;  // damping of the Jacobi iteration
  MultigridOptions multigrid;
};

class PoissonSolver {
 public:
  // dirichlet_walls: see PoissonOperator (-1: from bc).
  PoissonSolver(const GridShape& shape, Scalar h, Boundary bc, const std::uint8_t* solid,
                Scalar shift, const PoissonConfig& config, int dirichlet_walls = -1);

  // Solves A x = b from the initial guess in x. For a singular operator the component of b in
  // the null space is ignored and x is returned with zero mean per singular component.
  SolveInfo solve(const Scalar* b, Scalar* x, const IterativeOptions& options, Interrupt& interrupt);

  // Largest |mean(b)| / mean(|b|) over the singular components (0 when A is nonsingular): how
  // far b is from the range of A.
  Scalar incompatibility(const Scalar* b) const;

  const PoissonOperator& op() const { return *op_; }
  Multigrid* multigrid() { return mg_.get(); }
  Index default_max_iter() const;

 private:
  SolveInfo stationary(const Scalar* b, Scalar* x, const IterativeOptions& options,
                       Interrupt& interrupt);

  std::unique_ptr<PoissonOperator> op_;  // heap-held so the hierarchy's pointer stays valid
  std::unique_ptr<Multigrid> mg_;
  PoissonConfig config_;
  ScalarBuffer r_, z_, bp_, inv_diag_;
  CgWorkspace cg_;
};

}  // namespace kinema
