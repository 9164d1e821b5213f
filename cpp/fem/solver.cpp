#include "fem/solver.h"

#include <Eigen/Eigenvalues>
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
#include "fem/element_pass.h"
#include "linalg/cg.h"

namespace kinema::fem {

namespace {

Scalar dot(Index n, const Scalar* a, const Scalar* b) {
  return parallel_sum(n, [&](Index i) { return a[i] * b[i]; });
}

template <int D>
const Mat<D> dm_inv(const Model& m, Index e) {
  return Eigen::Map<const Mat<D>>(m.Dm_inv.data() + e * D * D);
}

// When the Newton matrix (a + b) M + s K is singular: if the stiffest row's s K / M exceeds
// 1 / eps_machine (4.5e15) the mass term is below the rounding of the stiffness one, so the
// rigid motions of an unpinned body are unresolvable in float64; says so, naming the inputs.
// s omega_max^2 / (a + b), omega_max^2 = 4 / dt_limit^2 (0 without a finite limit).
Scalar stiffness_ratio(Scalar dt_limit, Scalar s_over_a) {
  if (!(dt_limit > 0) || !std::isfinite(dt_limit)) return 0;
  return s_over_a * 4 / (dt_limit * dt_limit);
}

std::string stiffness_advice(Scalar dt_limit, Scalar s_over_a) {
  const Scalar ratio = stiffness_ratio(dt_limit, s_over_a);
  if (!(ratio > 1 / std::numeric_limits<Scalar>::epsilon())) return "";
  return ": dt^2 K / M reaches " + format_real(ratio) +
         ", beyond the 4.5e15 float64 resolves, so the mass term is lost to rounding (youngs_modulus "
         "too large for this density and dt); reduce dt, fix vertices, or choose other units";
}

}  // namespace

Solver::Solver(const Model& model, const Config& config)
    : model_(model),
      config_(config),
      assembly_(model_.vertex_count, model_.dim, model_.dim + 1, model_.elements.data(),
                model_.element_count) {
  element_vectors_.resize(model_.element_count * assembly_.element_vector_size());
  // omega_max^2 <= max_q sum_p |K_qp| / m_q at rest; the Hessian buffers are released again so
  // that an explicit-only body holds no matrix memory.
  std::vector<Scalar> values(assembly_.nonzeros());
  projected_hessian(model_.rest.data(), false, values.data());
  Scalar w2 = 0;
  const int d = model_.dim;
  for (Index q = 0; q < assembly_.dof_count(); ++q) {
    if (model_.fixed[q / d]) continue;
    Scalar row = 0;
    for (Index p = assembly_.row_ptr()[q]; p < assembly_.row_ptr()[q + 1]; ++p)
      row += std::abs(values[p]);
    w2 = std::max(w2, row / model_.mass[q / d]);
  }
  explicit_dt_limit_ = w2 > 0 ? 2 / std::sqrt(w2) : std::numeric_limits<Scalar>::infinity();
  for (Index e = 0; e < model_.element_count; ++e)
    energy_scale_ += model_.volume[e] * (2 * model_.mu[e] + std::abs(model_.lam[e])) * d;
  // Rigid motions are all held when the fixed vertices' rest positions span an affine set of
  // dimension >= d - 1 (two distinct points in 2D, three non-collinear ones in 3D).
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  Index first = -1;
  for (Index i = 0; i < model_.vertex_count; ++i) {
    if (!model_.fixed[i]) continue;
    if (first < 0) first = i;
    Eigen::Vector3d r = Eigen::Vector3d::Zero();
    for (int a = 0; a < d; ++a) r[a] = model_.rest[i * d + a] - model_.rest[first * d + a];
    scatter += r * r.transpose();
  }
  const Eigen::Vector3d ev = Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(scatter).eigenvalues();
  const int rank = static_cast<int>((ev.array() > 1e-12 * ev.maxCoeff()).count());
  rigid_motion_free_ = first < 0 || rank < d - 1;
  std::vector<Scalar>().swap(element_matrices_);
}


// ---------------------------------------------------------------- energies and derivatives

template <int D>
Scalar Solver::elastic_energy_d(const Scalar* x) const {
  const Model& m = model_;
  return parallel_sum(m.element_count, [&](Index e) {
    const Mat<D> F = deformation_gradient<D>(x, m.elements.data() + e * (D + 1), dm_inv<D>(m, e));
    return m.volume[e] * psi<D>(F, m.material(), m.mu[e], m.lam[e]);
  });
}

Scalar Solver::elastic_energy(const Scalar* x) const {
  return model_.dim == 2 ? elastic_energy_d<2>(x) : elastic_energy_d<3>(x);
}

Scalar Solver::kinetic_energy(const Scalar* v) const {
  return lumped_kinetic_energy(model_.mass.data(), v, model_.vertex_count, model_.dim);
}

Scalar Solver::gravity_energy(const Scalar* x) const {
  if (model_.gravity().empty()) return 0;
  const int d = model_.dim;
  return parallel_sum(model_.vertex_count, [&](Index i) {
    Scalar gx = 0;
    for (int r = 0; r < d; ++r) gx += model_.gravity()[r] * x[i * d + r];
    return -model_.mass[i] * gx;
  });
}

template <int D>
void Solver::elastic_gradient_d(const Scalar* x, Scalar* g) {
  const Model& m = model_;
  if (lanes::kAvailable && D == 3 && m.material() == Material::NeoHookean)
    lanes::neohookean_terms(m, lane_constants(), x, nullptr, avx2_, element_vectors_.data());
  else
    parallel_for(m.element_count, [&](Index e) { element_force_term<D>(m, x, e, element_vectors_.data()); });
  assembly_.gather_vector(element_vectors_.data(), g);
}

void Solver::elastic_gradient(const Scalar* x, Scalar* g) {
  if (model_.dim == 2) elastic_gradient_d<2>(x, g);
  else elastic_gradient_d<3>(x, g);
}

template <int D>
Index Solver::elastic_hessian_d(const Scalar* x, bool project, Scalar* values) {
  const Model& m = model_;
  constexpr int K = (D + 1) * D;
  if (element_matrices_.empty()) element_matrices_.resize(m.element_count * K * K);
  std::vector<unsigned char> clamped(project ? m.element_count : 0);
  parallel_for(m.element_count, [&](Index e) {
    const Mat<D> Dinv = dm_inv<D>(m, e);
    const Mat<D> F = deformation_gradient<D>(x, m.elements.data() + e * (D + 1), Dinv);
    HessF<D> H = piola_derivative<D>(F, m.material(), m.mu[e], m.lam[e]);
    if (project) clamped[e] = project_psd<D>(H);
    Eigen::Map<ElementMat<D>>(element_matrices_.data() + e * K * K) =
        element_hessian<D>(H, Dinv, m.volume[e]);
  });
  assembly_.gather_matrix(element_matrices_.data(), values);
  Index count = 0;
  for (unsigned char c : clamped) count += c;
  return count;
}

Index Solver::projected_hessian(const Scalar* x, bool project, Scalar* values) {
  return model_.dim == 2 ? elastic_hessian_d<2>(x, project, values)
                         : elastic_hessian_d<3>(x, project, values);
}

void Solver::forces(const Scalar* x, Scalar* f) {
  elastic_gradient(x, f);
  const int d = model_.dim;
  const bool gravity = !model_.gravity().empty();
  parallel_for(model_.vertex_count, [&](Index i) {
    for (int r = 0; r < d; ++r)
      f[i * d + r] = -f[i * d + r] + (gravity ? model_.mass[i] * model_.gravity()[r] : 0);
  });
}

void Solver::check_finite(const State& state, const std::vector<Scalar>& a,
                          const char* quantity) const {
  const Index bad = static_cast<Index>(
      parallel_sum(static_cast<Index>(a.size()), [&](Index i) { return std::isfinite(a[i]) ? 0.0 : 1.0; }));
  if (bad > 0)
    throw DivergenceError(std::string(quantity) + ": " + std::to_string(bad) +
                          " non-finite value(s) at step " + std::to_string(state.step) +
                          "; reduce dt (the symplectic limit is about " +
                          format_real(explicit_dt_limit()) + " s) or use integrator='implicit'");
}

// ---------------------------------------------------------------- time stepping

void Solver::check_config() const {
  const Config& c = config_;
  if (!(c.tol > 0) || !std::isfinite(c.tol))
    throw InvalidArgument("tol: expected a finite number > 0, got " + format_real(c.tol));
  if (c.max_newton < 1)
    throw InvalidArgument("max_newton: expected an integer >= 1, got " + std::to_string(c.max_newton));
  if (!(c.cg_tol > 0) || !std::isfinite(c.cg_tol))
    throw InvalidArgument("cg_tol: expected a finite number > 0, got " + format_real(c.cg_tol));
}

StepStats Solver::step(State& state, Scalar dt, Interrupt& interrupt, const Scalar* control) {
  if (!(dt > 0) || !std::isfinite(dt))
    throw InvalidArgument("dt: expected a finite time step > 0 [s], got " + format_real(dt));
  if (state.x.size() != model_.rest.size() || state.v.size() != model_.rest.size())
    throw InvalidArgument("state: x and v must hold " + std::to_string(model_.vertex_count) +
                          " vertices of the model");
  check_config();
  Stopwatch clock;
  StepStats stats = config_.integrator == Integrator::Symplectic
                        ? step_symplectic(state, dt, control)
                        : step_implicit(state, dt, control, interrupt);
  stats.time = state.time;
  stats.dt = dt;
  stats.seconds = clock.seconds();
  return stats;
}

StepStats Solver::step_symplectic(State& state, Scalar dt, const Scalar* control) {
  const Model& m = model_;
  const int d = m.dim;
  std::vector<Scalar>& g = grad_;
  g.resize(assembly_.dof_count());
  elastic_gradient(state.x.data(), g.data());
  // v_{n+1} = (v_n + dt M^-1 (f(x_n) + u)) / (1 + dt c), f = -grad E + M g: elastic and gravity
  // forces explicit, mass damping implicit (unconditionally stable on its own); then
  // x_{n+1} = x_n + dt v_{n+1}. One pass over the vertices, in place (each reads only its own
  // entries; a failed step is restored by the caller), counting non-finite results.
  const Scalar damp = 1 / (1 + dt * m.damping());
  const bool gravity = !m.gravity().empty();
  Scalar* x = state.x.data();
  Scalar* v = state.v.data();
  const Scalar bad = parallel_sum(m.vertex_count, [&](Index i) {
    Scalar count = 0;
    for (int r = 0; r < d; ++r) {
      const Index q = i * d + r;
      const Scalar f = -g[q] + (gravity ? m.mass[i] * m.gravity()[r] : 0);
      const Scalar fq = control ? f + control[q] : f;
      v[q] = m.fixed[i] ? 0 : (v[q] + dt * fq / m.mass[i]) * damp;
      x[q] += dt * v[q];
      count += std::isfinite(v[q]) && std::isfinite(x[q]) ? 0 : 1;
    }
    return count;
  });
  if (bad > 0) {
    check_finite(state, state.v, "v");
    check_finite(state, state.x, "x");
  }
  state.time += dt;
  ++state.step;
  StepStats stats;
  stats.converged = true;
  return stats;
}

StepStats Solver::step_implicit(State& state, Scalar dt, const Scalar* control,
                                Interrupt& interrupt) {
  const Model& m = model_;
  const Index n = assembly_.dof_count();
  const int d = m.dim;
  // Rigid motions the fixed vertices leave free are resolved by the mass term alone; past
  // dt^2 K / M = 1 / eps it is below the rounding of K's rows and the step would return
  // motion-free garbage (or a singular matrix): refused.
  const Scalar ratio = stiffness_ratio(explicit_dt_limit_, dt * dt);
  if (rigid_motion_free_ && ratio > 1 / std::numeric_limits<Scalar>::epsilon())
    throw InvalidArgument("youngs_modulus, dt: dt^2 K / M reaches " + format_real(ratio) +
                          " (E too large for this density and dt), beyond the 4.5e15 float64 resolves, "
                          "so the rigid motions its fixed vertices leave free are lost to rounding; reduce "
                          "dt, fix more vertices, or choose other units");
  // Inertial guess y = x_n + h v_n (fixed vertices stay where they are).
  std::vector<Scalar> y(n), x(n);
  parallel_for(m.vertex_count, [&](Index i) {
    for (int r = 0; r < d; ++r) {
      const Index q = i * d + r;
      y[q] = m.fixed[i] ? state.x[q] : state.x[q] + dt * state.v[q];
      x[q] = y[q];
    }
  });
  // x_{n+1} = argmin 1/2 ||x - y||_M^2 + h c/2 ||x - x_n||_M^2 + h^2 (E(x) - (M g + u) . x)
  StepStats stats = minimise(state, x.data(), y.data(), 1, state.x.data(), dt * m.damping(),
                             dt * dt, 1, control, config_, interrupt, "implicit step");
  // v_{n+1} = (x_{n+1} - x_n) / h
  std::vector<Scalar> v(n);
  parallel_for(n, [&](Index q) { v[q] = (x[q] - state.x[q]) / dt; });
  check_finite(state, v, "v");
  accept_step(state, x, v, dt);
  return stats;
}

StepStats Solver::solve_static(State& state, Index load_steps, Interrupt& interrupt) {
  if (model_.fixed_count == 0)
    throw InvalidArgument("fixed: solve_static needs fixed vertices (without them the body "
                          "has rigid motions and no unique equilibrium)");
  if (load_steps < 1)
    throw InvalidArgument("load_steps: expected an integer >= 1, got " + std::to_string(load_steps));
  check_config();
  std::vector<Scalar> x = state.x;
  StepStats total;
  Stopwatch clock;
  // Load stepping: equilibria for gravity scaled by k / load_steps, each the next one's guess.
  for (Index k = 1; k <= load_steps; ++k) {
    const Scalar load = Scalar(k) / Scalar(load_steps);
    StepStats s = minimise(state, x.data(), nullptr, 0, nullptr, 0, 1, load, nullptr, config_,
                           interrupt, "solve_static");
    total.iterations += s.iterations;
    total.gradient_norm.insert(total.gradient_norm.end(), s.gradient_norm.begin(),
                               s.gradient_norm.end());
    total.step_length.insert(total.step_length.end(), s.step_length.begin(), s.step_length.end());
    total.projected_elements = s.projected_elements;
    total.cg_iterations += s.cg_iterations;
    total.factorizations += s.factorizations;
    total.seconds_assembly += s.seconds_assembly;
    total.seconds_factor += s.seconds_factor;
    total.seconds_solve += s.seconds_solve;
    total.seconds_line_search += s.seconds_line_search;
    total.converged = s.converged;
  }
  total.seconds = clock.seconds();
  total.time = state.time;
  std::copy(x.begin(), x.end(), state.x.begin());  // in place: numpy views alias it
  std::fill(state.v.begin(), state.v.end(), 0);
  return total;
}

// ---------------------------------------------------------------- projected Newton

StepStats Solver::minimise(State& state, Scalar* x, const Scalar* y, Scalar a, const Scalar* z,
                           Scalar b, Scalar s, Scalar load, const Scalar* control,
                           const Config& options, Interrupt& interrupt, const char* what) {
  Stopwatch clock;
  StepStats stats;
  // The static solve's advice names its own options (load_steps, max_iter), not dt.
  const bool is_static = std::string(what) == "solve_static";
  const Model& m = model_;
  const Index n = assembly_.dof_count();
  const int d = m.dim;
  const bool gravity = !m.gravity().empty() && load != 0;
  grad_.resize(n);
  dx_.resize(n);
  trial_.resize(n);
  rhs_.resize(n);

  auto inertia = [&](const Scalar* xx) {
    if (a == 0 && b == 0) return Scalar(0);
    return parallel_sum(m.vertex_count, [&](Index i) {
      Scalar e = 0;
      for (int r = 0; r < d; ++r) {
        const Index q = i * d + r;
        if (a != 0) e += a * (xx[q] - y[q]) * (xx[q] - y[q]);
        if (b != 0) e += b * (xx[q] - z[q]) * (xx[q] - z[q]);
      }
      return m.mass[i] * e / 2;
    });
  };
  // - u . x over the free vertices (fixed ones ignore the control).
  auto control_energy = [&](const Scalar* xx) {
    return parallel_sum(m.vertex_count, [&](Index i) {
      Scalar e = 0;
      if (!m.fixed[i])
        for (int r = 0; r < d; ++r) e -= control[i * d + r] * xx[i * d + r];
      return e;
    });
  };
  auto objective = [&](const Scalar* xx) {
    Scalar potential = elastic_energy(xx) + (gravity ? load * gravity_energy(xx) : 0);
    if (control) potential += control_energy(xx);
    return inertia(xx) + s * potential;
  };
  // grad g on the free dofs (zero on fixed ones); returns its 2-norm.
  auto gradient = [&](const Scalar* xx, Scalar* g) {
    elastic_gradient(xx, g);
    parallel_for(m.vertex_count, [&](Index i) {
      for (int r = 0; r < d; ++r) {
        const Index q = i * d + r;
        if (m.fixed[i]) {
          g[q] = 0;
          continue;
        }
        Scalar external = gravity ? load * m.mass[i] * m.gravity()[r] : 0;
        if (control) external += control[q];
        Scalar v = s * (g[q] - external);
        if (a != 0) v += a * m.mass[i] * (xx[q] - y[q]);
        if (b != 0) v += b * m.mass[i] * (xx[q] - z[q]);
        g[q] = v;
      }
    });
    return std::sqrt(dot(n, g, g));
  };

  Stopwatch phase;
  Scalar g_norm = gradient(x, grad_.data());
  Scalar g_value = objective(x);
  stats.seconds_assembly += phase.seconds();
  if (!std::isfinite(g_norm) || !std::isfinite(g_value))
    throw DivergenceError(std::string(what) + ": non-finite energy or gradient at the initial "
                          "guess at step " + std::to_string(state.step) +
                          "; the state holds NaN/Inf or an extreme deformation");
  // Rounding level of the gradient: a few hundred ulps of the magnitudes of the terms summed
  // into it (element forces, inertia, load), which near a stiff equilibrium cancel by orders of
  // magnitude; below it the gradient norm is noise and Newton has converged.
  std::vector<Scalar> magnitude(n);
  auto noise_floor = [&](const Scalar* xx) {
    for (Scalar& v : element_vectors_) v = std::abs(v);  // holds xx's element gradients
    assembly_.gather_vector(element_vectors_.data(), magnitude.data());
    parallel_for(m.vertex_count, [&](Index i) {
      for (int r = 0; r < d; ++r) {
        const Index q = i * d + r;
        magnitude[q] = s * magnitude[q] + (a + b) * m.mass[i] * std::abs(xx[q]) +
                       (gravity ? s * std::abs(load * m.mass[i] * m.gravity()[r]) : 0);
        if (control && !m.fixed[i]) magnitude[q] += s * std::abs(control[q]);
      }
    });
    return 1e-13 * std::sqrt(dot(n, magnitude.data(), magnitude.data()));
  };
  Scalar floor = noise_floor(x);
  // Rounding level of the objective g: the relative part below, plus a few dozen ulps of the
  // sizes of the terms summed into it, which g's value does not show when they cancel or when
  // the strain is small: psi(F) ~ (2 mu + |lam|) d at |F| ~ 1 per unit volume whatever the
  // strain (a spinning body's elastic energy is noise of that size), and the load's - m g . x.
  Scalar value_terms = energy_scale_;
  if (gravity || control)
    value_terms += parallel_sum(m.vertex_count, [&](Index i) {
      Scalar t = 0;
      for (int r = 0; r < d; ++r) {
        const Index q = i * d + r;
        if (gravity) t += std::abs(load * m.mass[i] * m.gravity()[r] * x[q]);
        if (control && !m.fixed[i]) t += std::abs(control[q] * x[q]);
      }
      return t;
    });
  const Scalar value_noise = 64 * std::numeric_limits<Scalar>::epsilon() * s * value_terms;
  // Rounding of the positions themselves (x - x0 in Ds loses digits) through the stiffness:
  // ~ a few ulps of |H_qq x_q|, known once a Hessian has been assembled.
  Scalar position_noise = 0;
  const Scalar g0 = g_norm;
  stats.gradient_norm.push_back(g_norm);

  if (values_.empty()) values_.resize(assembly_.nonzeros());
  const auto& diag = assembly_.diagonal();
  if (options.linear_solver != LinearSolver::CG) sync_factor(state);

  for (Index it = 0; it < options.max_newton; ++it) {
    if (g_norm <= options.tol * g0 || g_norm <= floor + position_noise) {
      stats.converged = true;
      break;
    }
    interrupt.check();
    // Newton matrix (a + b) M + s K, exact or with the per-element definiteness fix.
    phase.restart();
    bool project = options.definiteness == Definiteness::Project ||
                   options.linear_solver == LinearSolver::CG;
    stats.projected_elements = assemble_newton_matrix(x, a + b, s, project);
    position_noise = 1e-15 * std::sqrt(parallel_sum(n, [&](Index q) {
      const Scalar t = values_[diag[q]] * std::abs(x[q]);
      return t * t;
    }));
    stats.seconds_assembly += phase.seconds();

    // Newton direction: H dx = -grad g, to the forcing tolerance eta (model.h, Config)
    const Scalar needed = std::max(options.tol * g0, floor + position_noise);
    const Scalar eta = options.linear_solver == LinearSolver::Cholmod
                           ? std::max(std::min(options.cg_tol, g_norm / g0), 0.1 * needed / g_norm)
                           : options.cg_tol;
    parallel_for(n, [&](Index q) { rhs_[q] = -grad_[q]; });
    auto solve = [&](bool reuse) {
      return linear_solve(state, options, rhs_.data(), dx_.data(), eta, reuse, x, a + b, s,
                          project, stats, interrupt);
    };
    bool solved = solve(true);
    if (!solved) {
      if (options.definiteness == Definiteness::None)
        throw NotPositiveDefinite(std::string(what) + ": the Newton matrix is indefinite at step " +
                                  std::to_string(state.step) +
                                  "; use the definiteness fix (definiteness='adaptive')", -1);
      phase.restart();
      project = true;
      stats.projected_elements = assemble_newton_matrix(x, a + b, s, project);
      stats.seconds_assembly += phase.seconds();
      if (!solve(true))
        throw ConvergenceError(std::string(what) + ": the projected Newton matrix is singular at "
                               "step " + std::to_string(state.step) +
                               (is_static ? " (rigid motions left free by the fixed vertices, or "
                                            "elements crushed flat by too large a load step: raise "
                                            "load_steps)"
                                          : stiffness_advice(explicit_dt_limit_, s / (a + b))));
    }
    Scalar slope = dot(n, grad_.data(), dx_.data());
    if (!(slope < 0) && options.linear_solver != LinearSolver::CG &&
        options.linear_solver != LinearSolver::CholmodDirect) {
      // A lagged preconditioner met an (exact, indefinite) matrix PCG cannot handle: factorise.
      if (!solve(false)) {
        phase.restart();
        project = true;
        stats.projected_elements = assemble_newton_matrix(x, a + b, s, project);
        stats.seconds_assembly += phase.seconds();
        solve(false);
      }
      slope = dot(n, grad_.data(), dx_.data());
    }
    if (!(slope < 0))
      throw ConvergenceError(std::string(what) + ": the Newton direction is not a descent "
                             "direction at step " + std::to_string(state.step) +
                             " (the linear solve failed); try linear_solver='cholmod_direct'");

    // Backtracking line search on g (Armijo, c = 1e-4). Near the solution g changes by less
    // than its rounding error (value_noise), so a step that lowers the gradient norm there is accepted too.
    phase.restart();
    Scalar alpha = 1;
    bool accepted = false;
    for (int halving = 0; halving < 40 && !accepted; ++halving, alpha /= 2) {
      parallel_for(n, [&](Index q) { trial_[q] = x[q] + alpha * dx_[q]; });
      const Scalar value = objective(trial_.data());
      if (!std::isfinite(value)) continue;
      if (value <= g_value + 1e-4 * alpha * slope) {
        accepted = true;
      } else if (std::abs(value - g_value) <=
                 1e-12 * (std::abs(g_value) + std::abs(value)) + value_noise) {
        std::vector<Scalar> g_trial(n);
        if (gradient(trial_.data(), g_trial.data()) < g_norm) accepted = true;
      }
      if (accepted) {
        std::copy(trial_.begin(), trial_.end(), x);
        g_value = value;
        stats.step_length.push_back(alpha);
      }
    }
    stats.seconds_line_search += phase.seconds();
    if (!accepted)
      throw ConvergenceError(std::string(what) + ": line search found no decrease at step " +
                             std::to_string(state.step) + " after " + std::to_string(it) +
                             " Newton iterations (relative gradient norm " + format_real(g_norm / g0) +
                             (is_static ? "); raise load_steps or loosen tol" : "); reduce dt or tol"));
    phase.restart();
    g_norm = gradient(x, grad_.data());
    floor = noise_floor(x);
    stats.seconds_assembly += phase.seconds();
    if (!std::isfinite(g_norm))
      throw DivergenceError(std::string(what) + ": non-finite gradient at step " +
                            std::to_string(state.step));
    stats.gradient_norm.push_back(g_norm);
    ++stats.iterations;
  }
  if (!stats.converged && (g_norm <= options.tol * g0 || g_norm <= floor + position_noise))
    stats.converged = true;
  if (!stats.converged)
    throw ConvergenceError(std::string(what) + ": Newton reached " +
                           (is_static ? "max_iter = " : "max_newton = ") +
                           std::to_string(options.max_newton) + " iterations at step " +
                           std::to_string(state.step) + " with relative gradient norm " +
                           format_real(g_norm / g0) + " > tol = " + format_real(options.tol) +
                           (is_static ? "; raise load_steps or max_iter" : "; reduce dt or raise max_newton"));
  stats.seconds = clock.seconds();
  return stats;
}

Index Solver::assemble_newton_matrix(const Scalar* x, Scalar a_plus_b, Scalar s, bool project) {
  const Model& m = model_;
  const int d = m.dim;
  const auto& row_ptr = assembly_.row_ptr();
  const auto& col = assembly_.col_index();
  const auto& diag = assembly_.diagonal();
  const Index projected = projected_hessian(x, project, values_.data());
  // Fixed dofs: identity rows/columns scaled by their diagonal (conditioning), zero rhs.
  parallel_for(m.vertex_count, [&](Index i) {
    for (int r = 0; r < d; ++r) {
      const Index q = i * d + r;
      for (Index p = row_ptr[q]; p < row_ptr[q + 1]; ++p) {
        values_[p] *= s;
        if ((m.fixed[i] || m.fixed[col[p] / d]) && p != diag[q]) values_[p] = 0;
      }
      values_[diag[q]] += a_plus_b * m.mass[i];
      if (m.fixed[i] && !(values_[diag[q]] > 0)) values_[diag[q]] = m.mass[i];
    }
  });
  return projected;
}

bool Solver::linear_solve(State& state, const Config& config, const Scalar* rhs, Scalar* dx,
                          Scalar tol, bool reuse, const Scalar* x, Scalar weight, Scalar scale,
                          bool projected, StepStats& stats, Interrupt& interrupt) {
  const Index n = assembly_.dof_count();
  const CsrView A{n, n, assembly_.row_ptr().data(), assembly_.col_index().data(), values_.data()};
  std::fill(dx, dx + n, 0);
  SpdSolveStats s;
  const bool cholmod = config.linear_solver != LinearSolver::CG;
  const bool ok = spd_.solve(config.linear_solver, A, rhs, dx, tol, reuse && !force_refactor_,
                            interrupt, s);
  stats.cg_iterations += s.cg_iterations;
  stats.factorizations += s.factorizations;
  stats.seconds_factor += s.seconds_factor;
  stats.seconds_solve += s.seconds_solve;
  if (!cholmod) return true;
  // Record which matrix the factor now is (a failed factorisation leaves none).
  if (s.factorizations > 0) {
    force_refactor_ = false;
    if (ok) factor_.x.assign(x, x + n);
    else factor_.x.clear();
    factor_.weight = ok ? weight : 0;
    factor_.scale = ok ? scale : 0;
    factor_.projected = ok && projected;
    factor_.refactor_pending = spd_.refactor_pending();
    state.factor = factor_;
  } else {
    factor_.refactor_pending = spd_.refactor_pending();
    state.factor.refactor_pending = factor_.refactor_pending;
  }
  return ok;
}

void Solver::sync_factor(const State& state) {
  const FactorRecord& r = state.factor;
  if (!force_refactor_ && r == factor_) return;
  if (r.x.empty() || r.refactor_pending) {
    force_refactor_ = true;  // the next solve factorises, as the recorded run's did
    return;
  }
  if (r.x.size() != model_.rest.size())
    throw InvalidArgument("state: factor_x must hold " + std::to_string(model_.vertex_count) +
                          " vertices of the model, or none");
  // Rebuild the recorded factor: the matrix at factor_x, factorised (the solve itself is spare).
  const Index n = assembly_.dof_count();
  assemble_newton_matrix(r.x.data(), r.weight, r.scale, r.projected);
  const CsrView A{n, n, assembly_.row_ptr().data(), assembly_.col_index().data(), values_.data()};
  std::vector<Scalar> zero(n, 0), out(n);
  SpdSolveStats s;
  if (spd_.solve_exact(A, zero.data(), out.data(), false, s)) {
    factor_ = r;
    force_refactor_ = false;
  } else {
    force_refactor_ = true;
  }
}

}  // namespace kinema::fem
