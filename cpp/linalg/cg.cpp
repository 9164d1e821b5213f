#include "linalg/cg.h"

#include <cmath>
#include <string>
#include <vector>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/timer.h"

namespace kinema {

namespace {

Scalar dot(Index n, const Scalar* a, const Scalar* b) {
  return parallel_sum(n, [&](Index i) { return a[i] * b[i]; });
}

}  // namespace

SolveInfo pcg(Index n, const LinearOperator& A, const LinearOperator& precond, const Scalar* b,
              Scalar* x, const IterativeOptions& options, Interrupt& interrupt,
              const std::function<void(Scalar*)>& project, CgWorkspace* workspace) {
  Stopwatch clock;
  SolveInfo info;
  const Index max_iter = options.max_iter > 0 ? options.max_iter : std::max<Index>(2 * n, 100);
  CgWorkspace local;
  CgWorkspace& w = workspace ? *workspace : local;
  for (auto* v : {&w.r, &w.z, &w.p, &w.q}) v->resize(n);
  ScalarBuffer &r = w.r, &z = w.z, &p = w.p, &q = w.q;

  const Scalar b_norm = std::sqrt(dot(n, b, b));
  if (b_norm == 0) {  // the solution of A x = 0 is x = 0
    parallel_for(n, [&](Index i) { x[i] = 0; });
    info.converged = true;
    info.history.push_back(0);
    info.seconds = clock.seconds();
    return info;
  }

  // r = b - A x0
  A(x, q.data());
  parallel_for(n, [&](Index i) { r[i] = b[i] - q[i]; });
  if (project) project(r.data());
  Scalar r_norm = std::sqrt(dot(n, r.data(), r.data()));
  info.history.push_back(r_norm / b_norm);

  Scalar rho = 0;
  for (Index it = 0; it < max_iter && r_norm > options.tol * b_norm; ++it) {
    interrupt.check();
    // z = M^-1 r; the preconditioned direction update (Saad, Alg. 9.1)
    if (precond) {
      precond(r.data(), z.data());
      if (project) project(z.data());
    } else {
      parallel_for(n, [&](Index i) { z[i] = r[i]; });
    }
    const Scalar rho_new = dot(n, r.data(), z.data());
    if (!std::isfinite(rho_new))
      throw DivergenceError("cg: non-finite residual at iteration " + std::to_string(it) +
                            "; check the matrix and right-hand side for NaN or Inf");
    const Scalar beta = it == 0 ? 0 : rho_new / rho;
    rho = rho_new;
    parallel_for(n, [&](Index i) { p[i] = z[i] + beta * p[i]; });
    A(p.data(), q.data());
    const Scalar pAp = dot(n, p.data(), q.data());
    if (!(pAp > 0))
      throw InvalidArgument("A: not positive definite (p^T A p = " + std::to_string(pAp) +
                            " at CG iteration " + std::to_string(it) + ")");
    const Scalar alpha = rho / pAp;
    parallel_for(n, [&](Index i) {
      x[i] += alpha * p[i];
      r[i] -= alpha * q[i];
    });
    r_norm = std::sqrt(dot(n, r.data(), r.data()));
    info.history.push_back(r_norm / b_norm);
    info.iterations = it + 1;
  }

  // Report the true residual, not the recursively updated one.
  if (project) project(x);
  A(x, q.data());
  parallel_for(n, [&](Index i) { r[i] = b[i] - q[i]; });
  if (project) project(r.data());
  info.residual = std::sqrt(dot(n, r.data(), r.data())) / b_norm;
  if (!std::isfinite(info.residual))
    throw DivergenceError("cg: non-finite solution; check the inputs for NaN or Inf");
  info.converged = r_norm <= options.tol * b_norm;
  info.seconds = clock.seconds();
  return info;
}

}  // namespace kinema
