// Geometric multigrid V-cycle for the cell-centred PoissonOperator, used alone ("multigrid")
// and as the preconditioner of conjugate gradients ("mgpcg"), after McAdams, Sifakis & Teran,
// "A parallel multigrid Poisson solver for fluids simulation on large grids" (SCA 2010):
// red-black Gauss-Seidel smoothing, coarse grids rediscretised at 2h (a coarse cell is fluid
// when any child is), trilinear prolongation P with the (1,3,3,1)/4 weights per axis and
// restriction R = P^T / 2^d. Pre- and post-smoothing run in opposite colour orders, so the
// V-cycle is a symmetric operator and a valid CG preconditioner. Boundaries enter P through
// ghost values: across a Dirichlet face the coarse value is mirrored with a sign change, across
// a Neumann face or into a solid cell it is copied; a periodic grid wraps around (and coarsens
// only while every active axis has an even number of cells, so the red-black colouring and the
// coarse cells stay consistent across the wrap). The coarsest grid is solved exactly (sparse
// LDL^T), with the null space of singular components projected out.
#pragma once

#include <memory>
#include <vector>

#include "core/buffer.h"
#include "poisson/poisson_operator.h"

namespace kinema {

struct MultigridOptions {
  int pre_smooth = 2;        // red-black sweeps before the coarse correction
  int post_smooth = 2;       // ... and after it
  Index coarsest_cells = 512;  // stop coarsening at or below this many cells
};

class Multigrid {
 public:
  Multigrid(const PoissonOperator& fine, const MultigridOptions& options = {});
  ~Multigrid();
  Multigrid(Multigrid&&) noexcept;
  Multigrid& operator=(Multigrid&&) noexcept;

  // x = V(b): one V-cycle from a zero initial guess, a fixed symmetric linear map of b.
  void vcycle(const Scalar* b, Scalar* x);

  int levels() const { return static_cast<int>(ops_.size()) + 1; }
  const PoissonOperator& level(int l) const { return l == 0 ? *fine_ : ops_[l - 1]; }

  // Grid transfers between level l and l + 1 (exposed for tests and benchmarks).
  void restrict_residual(int l, const Scalar* fine, Scalar* coarse) const;  // coarse = R fine
  void prolong_add(int l, const Scalar* coarse, Scalar* fine) const;        // fine += P coarse

 private:
  void cycle(int l, const Scalar* b, Scalar* x);
  void coarse_solve(const Scalar* b, Scalar* x);
  Scalar restrict_general(int l, const Scalar* fine, Index I, Index J, Index K) const;

  const PoissonOperator* fine_;       // owned by the caller, which outlives the hierarchy
  std::vector<PoissonOperator> ops_;  // coarse levels 1, 2, ...
  std::vector<ScalarBuffer> b_, x_, r_;
  MultigridOptions options_;
  struct Coarse;
  std::unique_ptr<Coarse> coarse_;
};

}  // namespace kinema
