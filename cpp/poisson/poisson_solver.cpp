#include "poisson/poisson_solver.h"

#include <cmath>

#include "core/parallel.h"
#include "core/timer.h"
#include "linalg/cg.h"

namespace kinema {

PoissonSolver::PoissonSolver(const GridShape& shape, Scalar h, Boundary bc,
                             const std::uint8_t* solid, Scalar shift, const PoissonConfig& config,
                             int dirichlet_walls)
    : op_(std::make_unique<PoissonOperator>(shape, h, bc, solid, shift, dirichlet_walls)), config_(config) {
  const MultigridOptions& mg = config_.multigrid;
  if (mg.pre_smooth < 0 || mg.post_smooth < 0 || mg.pre_smooth + mg.post_smooth < 1)
    throw InvalidArgument("pre_smooth, post_smooth: expected counts >= 0 with a positive sum, got " +
                          std::to_string(mg.pre_smooth) + " and " + std::to_string(mg.post_smooth));
  if (bc == Boundary::Periodic && config_.method != PoissonMethod::Jacobi && config_.method != PoissonMethod::CG)
    for (int a = 0; a < 3; ++a)
      if (shape.active(a) && shape.n[a] % 2 != 0)
        throw InvalidArgument("shape: red-black smoothing on a periodic grid needs an even number of cells "
                              "per axis (use method='cg' or 'jacobi' otherwise)");
  if (config_.method == PoissonMethod::Multigrid || config_.method == PoissonMethod::MGPCG)
    mg_ = std::make_unique<Multigrid>(*op_, config_.multigrid);
  r_.assign(op_->size(), 0);
  z_.assign(op_->size(), 0);
}

Index PoissonSolver::default_max_iter() const {
  Index longest = 1;
  for (int a = 0; a < 3; ++a) longest = std::max(longest, op_->shape().n[a]);
  switch (config_.method) {
    case PoissonMethod::Jacobi:
    case PoissonMethod::GaussSeidel: return 10000 + 10 * longest * longest;
    case PoissonMethod::CG: return 1000 + 20 * longest;
    default: return 500;
  }
}

Scalar PoissonSolver::incompatibility(const Scalar* b) const {
  if (!op_->singular()) return 0;
  // The projection removes exactly the null-space component; compare it with b's size.
  ScalarBuffer p(b, b + op_->size());
  op_->project(p.data());
  Scalar worst = 0;
  const Index n = op_->size();
  const Scalar abs_mean =
      parallel_sum(n, [&](Index c) { return op_->fluid(c) ? std::abs(b[c]) : 0.0; }) /
      std::max<Index>(op_->fluid_count(), 1);
  if (abs_mean == 0) return 0;
  for (Index c = 0; c < n; ++c)
    if (op_->fluid(c)) worst = std::max(worst, std::abs(b[c] - p[c]));
  return worst / abs_mean;
}

SolveInfo PoissonSolver::solve(const Scalar* b, Scalar* x, const IterativeOptions& options,
                               Interrupt& interrupt) {
  IterativeOptions opts = options;
  if (opts.max_iter <= 0) opts.max_iter = default_max_iter();
  const Index n = op_->size();
  op_->project(x);  // zero solid entries; remove the null-space part of the guess
  if (op_->singular() || op_->fluid_count() < n) {
    // Solid entries of b are ignored and its null-space component is not solvable: solve for
    // the projected right-hand side.
    bp_.assign(b, b + n);
    op_->project(bp_.data());
    b = bp_.data();
  }
  switch (config_.method) {
    case PoissonMethod::CG: {
      // Jacobi preconditioner: the operator's diagonal, zero on solid cells.
      if (inv_diag_.empty()) {
        inv_diag_.assign(n, 0);
        parallel_for(n, [&](Index c) {
          const Scalar d = op_->fluid(c) ? op_->diagonal(c) : 0;
          inv_diag_[c] = d > 0 ? 1 / d : 0;
        });
      }
      auto A = [&](const Scalar* in, Scalar* out) { op_->apply(in, out); };
      auto M = [&](const Scalar* in, Scalar* out) {
        parallel_for(n, [&](Index c) { out[c] = inv_diag_[c] * in[c]; });
      };
      std::function<void(Scalar*)> project;
      if (op_->singular() || op_->fluid_count() < n) project = [&](Scalar* v) { op_->project(v); };
      return pcg(n, A, M, b, x, opts, interrupt, project, &cg_);
    }
    case PoissonMethod::MGPCG: {
      auto A = [&](const Scalar* in, Scalar* out) { op_->apply(in, out); };
      auto M = [&](const Scalar* in, Scalar* out) { mg_->vcycle(in, out); };
      std::function<void(Scalar*)> project;
      if (op_->singular() || op_->fluid_count() < n) project = [&](Scalar* v) { op_->project(v); };
      return pcg(n, A, M, b, x, opts, interrupt, project, &cg_);
    }
    default:
      return stationary(b, x, opts, interrupt);
  }
}

// Jacobi, Gauss-Seidel and multigrid share the loop: update, then measure the residual.
SolveInfo PoissonSolver::stationary(const Scalar* b, Scalar* x, const IterativeOptions& opts,
                                    Interrupt& interrupt) {
  Stopwatch clock;
  SolveInfo info;
  const Index n = op_->size();
  const Scalar* bp = b;
  const Scalar b_norm = std::sqrt(parallel_sum(n, [&](Index c) { return bp[c] * bp[c]; }));
  if (b_norm == 0) {
    parallel_for(n, [&](Index c) { x[c] = 0; });
    info.converged = true;
    info.history.push_back(0);
    info.seconds = clock.seconds();
    return info;
  }
  auto residual_norm = [&] {
    op_->residual(bp, x, r_.data());
    if (op_->singular()) op_->project(r_.data());
    return std::sqrt(parallel_sum(n, [&](Index c) { return r_[c] * r_[c]; })) / b_norm;
  };
  Scalar rel = residual_norm();
  info.history.push_back(rel);
  while (rel > opts.tol && info.iterations < opts.max_iter) {
    interrupt.check();
    switch (config_.method) {
      case PoissonMethod::Jacobi:
        op_->jacobi(bp, x, z_.data(), config_.jacobi_omega);
        std::swap_ranges(z_.begin(), z_.end(), x);
        break;
      case PoissonMethod::GaussSeidel:
        op_->sweep(bp, x, 0);
        break;
      default:  // multigrid: x += V(b - A x), with r_ holding the residual just measured
        mg_->vcycle(r_.data(), z_.data());
        parallel_for(n, [&](Index c) { x[c] += z_[c]; });
        break;
    }
    if (op_->singular()) op_->project(x);
    rel = residual_norm();
    if (!std::isfinite(rel))
      throw DivergenceError("poisson: non-finite residual at iteration " +
                            std::to_string(info.iterations + 1));
    info.history.push_back(rel);
    ++info.iterations;
  }
  info.residual = rel;
  info.converged = rel <= opts.tol;
  info.seconds = clock.seconds();
  return info;
}

}  // namespace kinema
