#include "massspring/system.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <string>
#include <utility>

#include "core/errors.h"
#include "core/parallel.h"
#include "mesh/vertex_set.h"
#include "core/timer.h"
#include "linalg/cg.h"
#include "massspring/kernels.h"

namespace kinema::massspring {

namespace {

template <int D>
Vec<D> vertex(const std::vector<Scalar>& a, Index i) {
  return Eigen::Map<const Vec<D>>(a.data() + i * D);
}

}  // namespace

SystemModel make_system(int dim, Index vertex_count, const Index* springs, Index spring_count,
                        const Scalar* stiffness, const Scalar* rest_length, const Scalar* damping,
                        const Scalar* mass, const Index* fixed, Index fixed_count,
                        const std::vector<Scalar>& gravity) {
  if (dim != 2 && dim != 3) throw InvalidArgument("x: expected d = 2 or 3 columns");
  SystemModel m;
  m.dim = dim;
  m.vertex_count = vertex_count;
  m.spring_count = spring_count;
  m.springs.assign(springs, springs + 2 * spring_count);
  for (Index s = 0; s < spring_count; ++s) {
    const std::string at = "spring " + std::to_string(s);
    if (!(stiffness[s] >= 0) || !std::isfinite(stiffness[s]))
      throw InvalidArgument("stiffness: expected finite values >= 0, got " + format_real(stiffness[s]) +
                            " at " + at);
    if (!(rest_length[s] >= 0) || !std::isfinite(rest_length[s]))
      throw InvalidArgument("rest_length: expected finite values >= 0, got " +
                            format_real(rest_length[s]) + " at " + at);
    if (!(damping[s] >= 0) || !std::isfinite(damping[s]))
      throw InvalidArgument("damping: expected finite values >= 0, got " + format_real(damping[s]) +
                            " at " + at);
    m.any_damping = m.any_damping || damping[s] > 0;
  }
  for (Index i = 0; i < vertex_count; ++i)
    if (!(mass[i] > 0) || !std::isfinite(mass[i]))
      throw InvalidArgument("mass: expected finite values > 0, got " + format_real(mass[i]) +
                            " at vertex " + std::to_string(i));
  m.stiffness.assign(stiffness, stiffness + spring_count);
  m.rest_length.assign(rest_length, rest_length + spring_count);
  m.damping.assign(damping, damping + spring_count);
  m.mass.assign(mass, mass + vertex_count);
  m.fixed = vertex_flags(fixed, fixed_count, vertex_count, "fixed");
  bool any_gravity = false;
  if (!gravity.empty() && static_cast<int>(gravity.size()) != dim)
    throw InvalidArgument("gravity: expected " + std::to_string(dim) + " components");
  for (Scalar g : gravity) {
    if (!std::isfinite(g)) throw InvalidArgument("gravity: expected finite components");
    any_gravity = any_gravity || g != 0;
  }
  if (any_gravity) m.gravity = gravity;
  return m;
}

System::System(SystemModel model, const Scalar* x0)
    : model_(std::move(model)),
      assembly_(model_.vertex_count, model_.dim, 2, model_.springs.data(), model_.spring_count) {
  const Index n = assembly_.dof_count();
  state_.x.assign(x0, x0 + n);
  state_.v.assign(n, 0);
  element_vectors_.resize(model_.spring_count * assembly_.element_vector_size());
  f_.resize(n);
}

// ---------------------------------------------------------------- energies, forces

Scalar System::kinetic_energy() const {
  return lumped_kinetic_energy(model_.mass.data(), state_.v.data(), model_.vertex_count, model_.dim);
}

Scalar System::spring_energy() const {
  const int d = model_.dim;
  const auto& x = state_.x;
  return parallel_sum(model_.spring_count, [&](Index s) {
    const Index i = model_.springs[2 * s], j = model_.springs[2 * s + 1];
    Scalar l2 = 0;
    for (int r = 0; r < d; ++r) l2 += (x[j * d + r] - x[i * d + r]) * (x[j * d + r] - x[i * d + r]);
    const Scalar dl = std::sqrt(l2) - model_.rest_length[s];
    return model_.stiffness[s] / 2 * dl * dl;
  });
}

Scalar System::gravity_energy() const {
  if (model_.gravity.empty()) return 0;
  const int d = model_.dim;
  return parallel_sum(model_.vertex_count, [&](Index i) {
    Scalar gx = 0;
    for (int r = 0; r < d; ++r) gx += model_.gravity[r] * state_.x[i * d + r];
    return -model_.mass[i] * gx;
  });
}

template <int D>
void System::forces_d(Scalar* f, bool with_damping) {
  const SystemModel& m = model_;
  parallel_for(m.spring_count, [&](Index s) {
    const Index i = m.springs[2 * s], j = m.springs[2 * s + 1];
    const Vec<D> d = vertex<D>(state_.x, j) - vertex<D>(state_.x, i);
    const Vec<D> dv = vertex<D>(state_.v, j) - vertex<D>(state_.v, i);
    const Vec<D> fi = spring_force<D>(d, dv, m.stiffness[s], m.rest_length[s],
                                         with_damping ? m.damping[s] : 0);
    Scalar* out = element_vectors_.data() + s * 2 * D;
    for (int r = 0; r < D; ++r) {
      out[r] = fi(r);
      out[D + r] = -fi(r);
    }
  });
  assembly_.gather_vector(element_vectors_.data(), f);
  if (!m.gravity.empty())
    parallel_for(m.vertex_count, [&](Index i) {
      for (int r = 0; r < D; ++r) f[i * D + r] += m.mass[i] * m.gravity[r];
    });
}

void System::forces(Scalar* f) {
  if (model_.dim == 2) forces_d<2>(f, true);
  else forces_d<3>(f, true);
}

Scalar System::explicit_dt_limit() const {
  // omega^2 <= max_i sum_{springs at i} 2 k / m_i (Gershgorin on M^-1 K), dt < 2 / omega.
  std::vector<Scalar> row(model_.vertex_count, 0);
  for (Index s = 0; s < model_.spring_count; ++s)
    for (int a = 0; a < 2; ++a) row[model_.springs[2 * s + a]] += 2 * model_.stiffness[s];
  Scalar w2 = 0;
  for (Index i = 0; i < model_.vertex_count; ++i)
    if (!model_.fixed[i]) w2 = std::max(w2, row[i] / model_.mass[i]);
  return w2 > 0 ? 2 / std::sqrt(w2) : std::numeric_limits<Scalar>::infinity();
}

void System::check_finite(const std::vector<Scalar>& a, const char* quantity) const {
  for (Scalar v : a)
    if (!std::isfinite(v))
      throw DivergenceError(std::string(quantity) + ": non-finite value at step " +
                            std::to_string(state_.step) + "; the explicit limit is about dt < " +
                            format_real(explicit_dt_limit()) + " s: reduce dt or use integrator='implicit'");
}

// ---------------------------------------------------------------- implicit matrix

// values = M - h C - beta h^2 K, fixed rows/columns replaced by m_i I.
template <int D>
void System::assemble_d(Scalar dt, Scalar beta, bool clamp) {
  const SystemModel& m = model_;
  constexpr int K = 2 * D;
  if (element_matrices_.empty()) element_matrices_.resize(m.spring_count * K * K);
  if (values_.empty()) values_.resize(assembly_.nonzeros());
  parallel_for(m.spring_count, [&](Index s) {
    const Index i = m.springs[2 * s], j = m.springs[2 * s + 1];
    const Vec<D> d = vertex<D>(state_.x, j) - vertex<D>(state_.x, i);
    Mat<D> B = beta * dt * dt * m.stiffness[s] * spring_jacobian<D>(d, m.rest_length[s], clamp);
    if (m.damping[s] > 0) B += dt * m.damping[s] * spring_damping<D>(d);
    Eigen::Map<Eigen::Matrix<Scalar, K, K, Eigen::RowMajor>> E(element_matrices_.data() + s * K * K);
    E.template topLeftCorner<D, D>() = B;
    E.template bottomRightCorner<D, D>() = B;
    E.template topRightCorner<D, D>() = -B;
    E.template bottomLeftCorner<D, D>() = -B;
  });
  assembly_.gather_matrix(element_matrices_.data(), values_.data());
  const auto& row_ptr = assembly_.row_ptr();
  const auto& col = assembly_.col_index();
  const auto& diag = assembly_.diagonal();
  parallel_for(m.vertex_count, [&](Index i) {
    for (int r = 0; r < D; ++r) {
      const Index q = i * D + r;
      for (Index p = row_ptr[q]; p < row_ptr[q + 1]; ++p)
        if (m.fixed[i] || m.fixed[col[p] / D]) values_[p] = 0;
      values_[diag[q]] += m.mass[i];
    }
  });
}

// ---------------------------------------------------------------- step

StepStats System::step(Scalar dt, Integrator integrator, Scalar beta, LinearSolver solver,
                       Scalar cg_tol, Interrupt& interrupt) {
  Stopwatch clock, phase;
  StepStats stats;
  const SystemModel& m = model_;
  const int d = m.dim;
  const Index n = assembly_.dof_count();
  std::vector<Scalar> x = state_.x, v = state_.v;

  if (integrator != Integrator::Implicit) {
    // f(x_n, v_n); explicit Euler moves x with v_n, symplectic Euler with v_{n+1}.
    forces(f_.data());
    const bool symplectic = integrator == Integrator::Symplectic;
    parallel_for(m.vertex_count, [&](Index i) {
      for (int r = 0; r < d; ++r) {
        const Index q = i * d + r;
        if (m.fixed[i]) {
          v[q] = 0;
          continue;
        }
        const Scalar v_new = v[q] + dt * f_[q] / m.mass[i];
        x[q] += dt * (symplectic ? v_new : v[q]);
        v[q] = v_new;
      }
    });
  } else {
    // Elastic and gravity forces at x_n; damping enters the matrix, implicitly in v'.
    if (d == 2) forces_d<2>(f_.data(), false);
    else forces_d<3>(f_.data(), false);
    rhs_.resize(n);
    parallel_for(m.vertex_count, [&](Index i) {
      for (int r = 0; r < d; ++r) {
        const Index q = i * d + r;
        rhs_[q] = m.fixed[i] ? 0 : m.mass[i] * v[q] + dt * f_[q];  // M v + h f
      }
    });
    interrupt.check();
    // [M - h C - beta h^2 K] v' = M v + h f with the exact spring Jacobian; when it is not
    // positive definite (springs compressed far below rest length), the clamped one.
    const auto& row_ptr = assembly_.row_ptr();
    const auto& col = assembly_.col_index();
    for (int attempt = 0; attempt < 2; ++attempt) {
      const bool clamp = attempt == 1;
      stats.clamped = clamp;
      phase.restart();
      if (d == 2) assemble_d<2>(dt, beta, clamp);
      else assemble_d<3>(dt, beta, clamp);
      stats.seconds_assembly += phase.seconds();
      phase.restart();
      if (solver == LinearSolver::CG) {
        std::fill(v.begin(), v.end(), 0);
        const CsrView A{n, n, row_ptr.data(), col.data(), values_.data()};
        const SolveInfo info =
            cg_csr(A, rhs_.data(), v.data(), true, IterativeOptions{cg_tol, 0}, interrupt);
        stats.cg_iterations += info.iterations;
        stats.seconds_solve += phase.seconds();
        if (info.converged) break;
        if (clamp)
          throw ConvergenceError("implicit step: CG reached " + std::to_string(info.iterations) +
                                 " iterations with relative residual " + format_real(info.residual) +
                                 " at step " + std::to_string(state_.step) +
                                 "; use linear_solver='cholmod' or reduce dt");
        continue;
      }
      // CHOLMOD, the factor lagged across steps unless told otherwise (PCG starts from v' = v).
      LaggedSolveStats s;
      const CsrView A{n, n, row_ptr.data(), col.data(), values_.data()};
      const bool lagged = solver != LinearSolver::CholmodDirect;
      const bool ok = factor_.solve(A, rhs_.data(), v.data(), lagged, cg_tol, 25, s);
      stats.cg_iterations += s.pcg_iterations;
      stats.factorizations += s.factorizations;
      stats.refactored = stats.factorizations > 0;
      stats.seconds_factor += s.seconds_factor;
      stats.seconds_solve += s.seconds_solve;
      if (ok) break;
      if (clamp)
        throw NotPositiveDefinite("implicit step: the clamped implicit matrix is not positive "
                                  "definite at step " + std::to_string(state_.step) +
                                  "; check for negative stiffness or reduce dt", -1);
    }
    // x' = x + h v'
    parallel_for(n, [&](Index q) { x[q] += dt * v[q]; });
  }
  check_finite(v, "v");
  check_finite(x, "x");
  accept_step(state_, x, v, dt);
  stats.seconds = clock.seconds();
  return stats;
}

}  // namespace kinema::massspring
