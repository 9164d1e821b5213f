#include "fem/body.h"

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

namespace kinema::fem {

namespace {

Scalar dot(Index n, const Scalar* a, const Scalar* b) {
  return parallel_sum(n, [&](Index i) { return a[i] * b[i]; });
}

template <int D>
const Mat<D> dm_inv(const BodyModel& m, Index e) {
  return Eigen::Map<const Mat<D>>(m.Dm_inv.data() + e * D * D);
}

template <int D>
void build_rest_shape(BodyModel& m) {
  m.Dm_inv.resize(m.element_count * D * D);
  m.volume.resize(m.element_count);
  m.min_edge = std::numeric_limits<Scalar>::infinity();
  Scalar scale = 0;  // largest edge, for the degeneracy threshold
  for (Index e = 0; e < m.element_count; ++e) {
    const Index* el = m.elements.data() + e * (D + 1);
    for (int a = 0; a <= D; ++a)
      for (int b = a + 1; b <= D; ++b) {
        Scalar len2 = 0;
        for (int r = 0; r < D; ++r) {
          const Scalar t = m.rest[el[a] * D + r] - m.rest[el[b] * D + r];
          len2 += t * t;
        }
        m.min_edge = std::min(m.min_edge, std::sqrt(len2));
        scale = std::max(scale, std::sqrt(len2));
      }
  }
  for (Index e = 0; e < m.element_count; ++e) {
    const Index* el = m.elements.data() + e * (D + 1);
    Mat<D> Dinv;
    const Scalar vol = rest_shape<D>(m.rest.data(), el, Dinv);
    // Degenerate when the volume is negligible next to the element's own edge lengths.
    Scalar longest = 0;
    for (int a = 0; a <= D; ++a)
      for (int b = a + 1; b <= D; ++b) {
        Scalar len2 = 0;
        for (int r = 0; r < D; ++r) {
          const Scalar t = m.rest[el[a] * D + r] - m.rest[el[b] * D + r];
          len2 += t * t;
        }
        longest = std::max(longest, std::sqrt(len2));
      }
    if (!(std::abs(vol) > 1e-12 * std::pow(longest, D)) || !Dinv.allFinite())
      throw InvalidArgument("elements: element " + std::to_string(e) +
                            " is degenerate (rest " + (D == 2 ? "area " : "volume ") + format_real(vol) +
                            "); remove it or fix its vertices");
    if (vol < 0)
      throw InvalidArgument("elements: element " + std::to_string(e) +
                            " is inverted in the rest shape (signed " +
                            (D == 2 ? "area " : "volume ") + format_real(vol) +
                            "); swap two of its vertices to orient it positively");
    m.volume[e] = vol;
    Eigen::Map<Mat<D>>(m.Dm_inv.data() + e * D * D) = Dinv;
  }
  (void)scale;
}

}  // namespace

BodyModel make_model(int dim, const Scalar* rest, Index vertex_count, const Index* elements,
                     Index element_count, const BodyConfig& config, const Index* fixed,
                     Index fixed_count) {
  if (dim != 2 && dim != 3) throw InvalidArgument("vertices: expected d = 2 or 3 columns");
  if (element_count < 1) throw InvalidArgument("elements: expected at least one element");
  const Scalar E = config.youngs_modulus, nu = config.poisson_ratio, rho = config.density;
  if (!(E > 0) || !std::isfinite(E))
    throw InvalidArgument("youngs_modulus: expected a finite number > 0, got " + format_real(E));
  if (!(nu > -1 && nu < 0.5))
    throw InvalidArgument("poisson_ratio: expected a number in (-1, 0.5), got " + format_real(nu));
  if (!(rho > 0) || !std::isfinite(rho))
    throw InvalidArgument("density: expected a finite number > 0, got " + format_real(rho));
  if (!(config.damping >= 0) || !std::isfinite(config.damping))
    throw InvalidArgument("damping: expected a finite number >= 0, got " + format_real(config.damping));
  if (!config.gravity.empty() && static_cast<int>(config.gravity.size()) != dim)
    throw InvalidArgument("gravity: expected " + std::to_string(dim) + " components");

  BodyModel m;
  m.dim = dim;
  m.vertex_count = vertex_count;
  m.element_count = element_count;
  m.material = config.material;
  lame(E, nu, m.mu, m.lam);
  m.damping = config.damping;
  m.rest.assign(rest, rest + vertex_count * dim);
  m.elements.assign(elements, elements + element_count * (dim + 1));
  for (Index s = 0; s < element_count * (dim + 1); ++s)
    if (elements[s] < 0 || elements[s] >= vertex_count)
      throw InvalidArgument("elements: element " + std::to_string(s / (dim + 1)) +
                            " refers to vertex " + std::to_string(elements[s]) +
                            ", outside [0, " + std::to_string(vertex_count) + ")");
  if (dim == 2) build_rest_shape<2>(m);
  else build_rest_shape<3>(m);

  // Lumped masses: each element gives rho V / (d + 1) to each of its vertices.
  m.mass.assign(vertex_count, 0);
  for (Index e = 0; e < element_count; ++e)
    for (int a = 0; a <= dim; ++a)
      m.mass[m.elements[e * (dim + 1) + a]] += rho * m.volume[e] / (dim + 1);
  for (Index i = 0; i < vertex_count; ++i)
    if (m.mass[i] == 0)
      throw InvalidArgument("vertices: vertex " + std::to_string(i) +
                            " belongs to no element (it would have no mass)");

  m.fixed = vertex_flags(fixed, fixed_count, vertex_count, "fixed");
  for (Index i = 0; i < vertex_count; ++i) m.fixed_count += m.fixed[i];

  bool any_gravity = false;
  for (Scalar g : config.gravity) {
    if (!std::isfinite(g)) throw InvalidArgument("gravity: expected finite components");
    any_gravity = any_gravity || g != 0;
  }
  if (any_gravity) m.gravity = config.gravity;
  m.wave_speed = std::sqrt((m.lam + 2 * m.mu) / rho);
  return m;
}

Body::Body(BodyModel model, const BodyConfig& config)
    : model_(std::move(model)),
      assembly_(model_.vertex_count, model_.dim, model_.dim + 1, model_.elements.data(),
                model_.element_count) {
  (void)config;
  state_.x = model_.rest;
  state_.v.assign(model_.rest.size(), 0);
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
  std::vector<Scalar>().swap(element_matrices_);
}


// ---------------------------------------------------------------- energies and derivatives

template <int D>
Scalar Body::elastic_energy_d(const Scalar* x) const {
  const BodyModel& m = model_;
  return parallel_sum(m.element_count, [&](Index e) {
    const Mat<D> F = deformation_gradient<D>(x, m.elements.data() + e * (D + 1), dm_inv<D>(m, e));
    return m.volume[e] * psi<D>(F, m.material, m.mu, m.lam);
  });
}

Scalar Body::elastic_energy(const Scalar* x) const {
  return model_.dim == 2 ? elastic_energy_d<2>(x) : elastic_energy_d<3>(x);
}

Scalar Body::kinetic_energy() const {
  return lumped_kinetic_energy(model_.mass.data(), state_.v.data(), model_.vertex_count, model_.dim);
}

Scalar Body::gravity_energy(const Scalar* x) const {
  if (model_.gravity.empty()) return 0;
  const int d = model_.dim;
  return parallel_sum(model_.vertex_count, [&](Index i) {
    Scalar gx = 0;
    for (int r = 0; r < d; ++r) gx += model_.gravity[r] * x[i * d + r];
    return -model_.mass[i] * gx;
  });
}

template <int D>
void Body::elastic_gradient_d(const Scalar* x, Scalar* g) {
  const BodyModel& m = model_;
  constexpr int K = (D + 1) * D;
  parallel_for(m.element_count, [&](Index e) {
    const Mat<D> Dinv = dm_inv<D>(m, e);
    const Mat<D> F = deformation_gradient<D>(x, m.elements.data() + e * (D + 1), Dinv);
    const Mat<D> P = piola<D>(F, m.material, m.mu, m.lam);
    Eigen::Map<ElementVec<D>>(element_vectors_.data() + e * K) =
        element_gradient<D>(P, Dinv, m.volume[e]);
  });
  assembly_.gather_vector(element_vectors_.data(), g);
}

void Body::elastic_gradient(const Scalar* x, Scalar* g) {
  if (model_.dim == 2) elastic_gradient_d<2>(x, g);
  else elastic_gradient_d<3>(x, g);
}

template <int D>
Index Body::elastic_hessian_d(const Scalar* x, bool project, Scalar* values) {
  const BodyModel& m = model_;
  constexpr int K = (D + 1) * D;
  if (element_matrices_.empty()) element_matrices_.resize(m.element_count * K * K);
  std::vector<unsigned char> clamped(project ? m.element_count : 0);
  parallel_for(m.element_count, [&](Index e) {
    const Mat<D> Dinv = dm_inv<D>(m, e);
    const Mat<D> F = deformation_gradient<D>(x, m.elements.data() + e * (D + 1), Dinv);
    HessF<D> H = piola_derivative<D>(F, m.material, m.mu, m.lam);
    if (project) clamped[e] = project_psd<D>(H);
    Eigen::Map<ElementMat<D>>(element_matrices_.data() + e * K * K) =
        element_hessian<D>(H, Dinv, m.volume[e]);
  });
  assembly_.gather_matrix(element_matrices_.data(), values);
  Index count = 0;
  for (unsigned char c : clamped) count += c;
  return count;
}

Index Body::projected_hessian(const Scalar* x, bool project, Scalar* values) {
  return model_.dim == 2 ? elastic_hessian_d<2>(x, project, values)
                         : elastic_hessian_d<3>(x, project, values);
}

void Body::forces(const Scalar* x, Scalar* f) {
  elastic_gradient(x, f);
  const int d = model_.dim;
  const bool gravity = !model_.gravity.empty();
  parallel_for(model_.vertex_count, [&](Index i) {
    for (int r = 0; r < d; ++r)
      f[i * d + r] = -f[i * d + r] + (gravity ? model_.mass[i] * model_.gravity[r] : 0);
  });
}

void Body::check_finite(const std::vector<Scalar>& a, const char* quantity) const {
  const Index bad = static_cast<Index>(
      parallel_sum(static_cast<Index>(a.size()), [&](Index i) { return std::isfinite(a[i]) ? 0.0 : 1.0; }));
  if (bad > 0)
    throw DivergenceError(std::string(quantity) + ": " + std::to_string(bad) +
                          " non-finite value(s) at step " + std::to_string(state_.step) +
                          "; reduce dt (the symplectic limit is about " +
                          format_real(explicit_dt_limit()) + " s) or use integrator='implicit'");
}

// ---------------------------------------------------------------- time stepping

void Body::step_symplectic(Scalar dt) {
  const BodyModel& m = model_;
  const int d = m.dim;
  std::vector<Scalar>& f = grad_;
  f.resize(assembly_.dof_count());
  std::vector<Scalar> x = state_.x, v = state_.v;
  // v_{n+1} = (v_n + dt M^-1 f(x_n)) / (1 + dt c): elastic and gravity forces explicit,
  // mass damping implicit (unconditionally stable on its own).
  forces(x.data(), f.data());
  const Scalar damp = 1 / (1 + dt * m.damping);
  parallel_for(m.vertex_count, [&](Index i) {
    for (int r = 0; r < d; ++r) {
      const Index q = i * d + r;
      v[q] = m.fixed[i] ? 0 : (v[q] + dt * f[q] / m.mass[i]) * damp;
      x[q] += dt * v[q];  // x_{n+1} = x_n + dt v_{n+1}
    }
  });
  check_finite(v, "v");
  check_finite(x, "x");
  accept_step(state_, x, v, dt);
}

NewtonStats Body::step_implicit(Scalar dt, const NewtonOptions& options, Interrupt& interrupt) {
  const BodyModel& m = model_;
  const Index n = assembly_.dof_count();
  const int d = m.dim;
  // Inertial guess y = x_n + h v_n (fixed vertices stay where they are).
  std::vector<Scalar> y(n), x(n);
  parallel_for(m.vertex_count, [&](Index i) {
    for (int r = 0; r < d; ++r) {
      const Index q = i * d + r;
      y[q] = m.fixed[i] ? state_.x[q] : state_.x[q] + dt * state_.v[q];
      x[q] = y[q];
    }
  });
  // x_{n+1} = argmin 1/2 ||x - y||_M^2 + h c/2 ||x - x_n||_M^2 + h^2 (E(x) - M g . x)
  NewtonStats stats = minimise(x.data(), y.data(), 1, state_.x.data(), dt * m.damping, dt * dt,
                               1, options, interrupt, "implicit step");
  // v_{n+1} = (x_{n+1} - x_n) / h
  std::vector<Scalar> v(n);
  parallel_for(n, [&](Index q) { v[q] = (x[q] - state_.x[q]) / dt; });
  check_finite(v, "v");
  accept_step(state_, x, v, dt);
  return stats;
}

NewtonStats Body::solve_static(const NewtonOptions& options, Index load_steps,
                               Interrupt& interrupt) {
  if (model_.fixed_count == 0)
    throw InvalidArgument("fixed: solve_static needs fixed vertices (without them the body "
                          "has rigid motions and no unique equilibrium)");
  std::vector<Scalar> x = state_.x;
  NewtonStats total;
  Stopwatch clock;
  // Load stepping: equilibria for gravity scaled by k / load_steps, each the next one's guess.
  for (Index k = 1; k <= load_steps; ++k) {
    const Scalar load = Scalar(k) / Scalar(load_steps);
    NewtonStats s = minimise(x.data(), nullptr, 0, nullptr, 0, 1, load, options, interrupt,
                             "solve_static");
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
  std::copy(x.begin(), x.end(), state_.x.begin());  // in place: numpy views alias it
  std::fill(state_.v.begin(), state_.v.end(), 0);
  return total;
}

// ---------------------------------------------------------------- projected Newton

NewtonStats Body::minimise(Scalar* x, const Scalar* y, Scalar a, const Scalar* z, Scalar b,
                           Scalar s, Scalar load, const NewtonOptions& options,
                           Interrupt& interrupt, const char* what) {
  Stopwatch clock;
  NewtonStats stats;
  const BodyModel& m = model_;
  const Index n = assembly_.dof_count();
  const int d = m.dim;
  const bool gravity = !m.gravity.empty() && load != 0;
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
  auto objective = [&](const Scalar* xx) {
    return inertia(xx) + s * (elastic_energy(xx) + (gravity ? load * gravity_energy(xx) : 0));
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
        Scalar v = s * (g[q] - (gravity ? load * m.mass[i] * m.gravity[r] : 0));
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
                          "guess at step " + std::to_string(state_.step) +
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
                       (gravity ? s * std::abs(load * m.mass[i] * m.gravity[r]) : 0);
      }
    });
    return 1e-13 * std::sqrt(dot(n, magnitude.data(), magnitude.data()));
  };
  Scalar floor = noise_floor(x);
  // Rounding of the positions themselves (x - x0 in Ds loses digits) through the stiffness:
  // ~ a few ulps of |H_qq x_q|, known once a Hessian has been assembled.
  Scalar position_noise = 0;
  const Scalar g0 = g_norm;
  stats.gradient_norm.push_back(g_norm);

  if (values_.empty()) values_.resize(assembly_.nonzeros());
  const auto& diag = assembly_.diagonal();

  for (Index it = 0; it < options.max_iter; ++it) {
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

    // Newton direction: H dx = -grad g, to the forcing tolerance eta (body.h)
    const Scalar needed = std::max(options.tol * g0, floor + position_noise);
    const Scalar eta = options.linear_solver == LinearSolver::Cholmod
                           ? std::max(std::min(options.cg_tol, g_norm / g0), 0.1 * needed / g_norm)
                           : options.cg_tol;
    parallel_for(n, [&](Index q) { rhs_[q] = -grad_[q]; });
    bool solved = linear_solve(options, rhs_.data(), dx_.data(), eta, true, stats);
    if (!solved) {
      if (options.definiteness == Definiteness::None)
        throw NotPositiveDefinite(std::string(what) + ": the Newton matrix is indefinite at step " +
                                  std::to_string(state_.step) +
                                  "; use the definiteness fix (definiteness='adaptive')", -1);
      phase.restart();
      stats.projected_elements = assemble_newton_matrix(x, a + b, s, true);
      stats.seconds_assembly += phase.seconds();
      if (!linear_solve(options, rhs_.data(), dx_.data(), eta, true, stats))
        throw ConvergenceError(std::string(what) + ": the projected Newton matrix is singular at "
                               "step " + std::to_string(state_.step) +
                               " (are rigid motions left free in a static solve?)");
    }
    Scalar slope = dot(n, grad_.data(), dx_.data());
    if (!(slope < 0) && options.linear_solver != LinearSolver::CG &&
        options.linear_solver != LinearSolver::CholmodDirect) {
      // A lagged preconditioner met an (exact, indefinite) matrix PCG cannot handle: factorise.
      if (!linear_solve(options, rhs_.data(), dx_.data(), eta, false, stats)) {
        phase.restart();
        stats.projected_elements = assemble_newton_matrix(x, a + b, s, true);
        stats.seconds_assembly += phase.seconds();
        linear_solve(options, rhs_.data(), dx_.data(), eta, false, stats);
      }
      slope = dot(n, grad_.data(), dx_.data());
    }
    if (!(slope < 0))
      throw ConvergenceError(std::string(what) + ": the Newton direction is not a descent "
                             "direction at step " + std::to_string(state_.step) +
                             " (the linear solve failed); try linear_solver='cholmod_direct'");

    // Backtracking line search on g (Armijo, c = 1e-4). Near the solution g changes by less
    // than its rounding error, so a step that lowers the gradient norm there is accepted too.
    phase.restart();
    Scalar alpha = 1;
    bool accepted = false;
    for (int halving = 0; halving < 40 && !accepted; ++halving, alpha /= 2) {
      parallel_for(n, [&](Index q) { trial_[q] = x[q] + alpha * dx_[q]; });
      const Scalar value = objective(trial_.data());
      if (!std::isfinite(value)) continue;
      if (value <= g_value + 1e-4 * alpha * slope) {
        accepted = true;
      } else if (std::abs(value - g_value) <= 1e-12 * (std::abs(g_value) + std::abs(value))) {
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
                             std::to_string(state_.step) + " after " + std::to_string(it) +
                             " Newton iterations (relative gradient norm " + format_real(g_norm / g0) +
                             "); reduce dt or tol");
    phase.restart();
    g_norm = gradient(x, grad_.data());
    floor = noise_floor(x);
    stats.seconds_assembly += phase.seconds();
    if (!std::isfinite(g_norm))
      throw DivergenceError(std::string(what) + ": non-finite gradient at step " +
                            std::to_string(state_.step));
    stats.gradient_norm.push_back(g_norm);
    ++stats.iterations;
  }
  if (!stats.converged && (g_norm <= options.tol * g0 || g_norm <= floor + position_noise))
    stats.converged = true;
  if (!stats.converged)
    throw ConvergenceError(std::string(what) + ": Newton reached max_newton = " +
                           std::to_string(options.max_iter) + " iterations at step " +
                           std::to_string(state_.step) + " with relative gradient norm " +
                           format_real(g_norm / g0) + " > tol = " + format_real(options.tol) +
                           "; reduce dt or raise max_newton");
  stats.seconds = clock.seconds();
  return stats;
}

Index Body::assemble_newton_matrix(const Scalar* x, Scalar a_plus_b, Scalar s, bool project) {
  const BodyModel& m = model_;
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

bool Body::linear_solve(const NewtonOptions& options, const Scalar* rhs, Scalar* dx, Scalar tol,
                        bool reuse, NewtonStats& stats) {
  const Index n = assembly_.dof_count();
  const CsrView A{n, n, assembly_.row_ptr().data(), assembly_.col_index().data(), values_.data()};
  if (options.linear_solver == LinearSolver::CG) {
    Stopwatch phase;
    std::fill(dx, dx + n, 0);
    Interrupt none;
    const SolveInfo info = cg_csr(A, rhs, dx, true, IterativeOptions{tol, 0}, none);
    stats.cg_iterations += info.iterations;
    stats.seconds_solve += phase.seconds();
    return true;
  }
  // CHOLMOD: symbolic analysis once per body; the numeric factor refreshed as the solver says.
  LaggedSolveStats s;
  const bool lagged = reuse && options.linear_solver != LinearSolver::CholmodDirect;
  std::fill(dx, dx + n, 0);
  const bool ok = factor_.solve(A, rhs, dx, lagged, tol, 25, s);
  stats.cg_iterations += s.pcg_iterations;
  stats.factorizations += s.factorizations;
  stats.seconds_factor += s.seconds_factor;
  stats.seconds_solve += s.seconds_solve;
  return ok;
}

}  // namespace kinema::fem
