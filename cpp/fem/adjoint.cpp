// The adjoint (vector-Jacobian product) of one step of fem/solver.h, for reverse-mode gradients
// of whole runs (python/kinema/diff.py). With a = dL/dx_{n+1}, b = dL/dv_{n+1}:
//   symplectic  w = h/(m (1 + h c)) (b + h a) on free vertices (0 on fixed ones);
//               dL/dx_n = a - K(x_n) w,  dL/dv_n = (b + h a)/(1 + h c),  dL/du = w,
//               dL/dtheta = w . df/dtheta.
//   implicit    the minimiser satisfies G(x_{n+1}, theta) = grad g = 0 on the free dofs, so
//               (implicit function theorem) H lambda = a + b/h with the exact Hessian
//               H = (1 + h c) M + h^2 K(x_{n+1}) and dL/dtheta = -lambda . dG/dtheta:
//               dL/dx_n = (1 + h c) M lambda - b/h (free), a - h^2 K lambda (fixed),
//               dL/dv_n = h M lambda,  dL/du = h^2 lambda.
// The adjoint solve reaches a relative residual of 1e-10 (PCG with the forward step's own
// preconditioner, or a CHOLMOD factorisation of H).
// Element parameters enter through P = mu A(F) + lam B(F) (fem/kernels.h), chained to
// (E, nu) by mu = E / (2 (1 + nu)), lam = E nu / ((1 + nu)(1 - 2 nu)).
// The implicit adjoint is the derivative of the exact minimiser: the definiteness fix and the
// line search change Newton's path to it, not the point it converges to, so they do not enter;
// the result differs from the derivative of the computed step by O(tol) (Newton's stopping test).
#include <algorithm>
#include <cmath>
#include <string>

#include "core/errors.h"
#include "core/parallel.h"
#include "fem/element_pass.h"
#include "fem/solver.h"
#include "linalg/cg.h"

namespace kinema::fem {

namespace {

// Relative residual of the adjoint solve H lambda = rhs: four orders below the O(tol) (1e-6 by
// default) by which Newton's answer differs from the exact minimiser, so the gradient's error
// is Newton's, not the solve's.
constexpr Scalar kAdjointTolerance = 1e-10;

// sum over the free dofs q = i d + r of term(i, q, r).
template <class Term>
Scalar free_dof_sum(const Model& m, Term&& term) {
  const int d = m.dim;
  return parallel_sum(m.vertex_count, [&](Index i) {
    Scalar t = 0;
    if (!m.fixed[i])
      for (int r = 0; r < d; ++r) t += term(i, i * d + r, r);
    return t;
  });
}

template <int D>
Mat<D> dm_inverse(const Model& m, Index e) {
  return Eigen::Map<const Mat<D>>(m.Dm_inv.data() + e * D * D);
}

}  // namespace

void Solver::hessian_product(const Scalar* x, const Scalar* w, Scalar* out) {
  if (model_.dim == 2) adjoint_elements_d<2>(x, w, out, nullptr, nullptr, false);
  else adjoint_elements_d<3>(x, w, out, nullptr, nullptr, false);
}

template <int D>
void Solver::parameter_product_d(const Scalar* x, const Scalar* w, Scalar* g_mu,
                                 Scalar* g_lam) const {
  const Model& m = model_;
  parallel_for(m.element_count, [&](Index e) {
    const Index* el = m.elements.data() + e * (D + 1);
    const Mat<D> Dinv = dm_inverse<D>(m, e);
    const Mat<D> F = deformation_gradient<D>(x, el, Dinv);
    const Mat<D> dF = deformation_gradient<D>(w, el, Dinv);
    Mat<D> A, B;
    piola_lame_derivatives<D>(F, m.material(), A, B);
    // w . d(vol P Dm^-T)/dmu over the element's vertices = vol A : Ds(w) Dm^-1.
    g_mu[e] = m.volume[e] * A.cwiseProduct(dF).sum();
    g_lam[e] = m.volume[e] * B.cwiseProduct(dF).sum();
  });
}

void Solver::parameter_product(const Scalar* x, const Scalar* w, Scalar* g_mu,
                               Scalar* g_lam) const {
  if (model_.dim == 2) parameter_product_d<2>(x, w, g_mu, g_lam);
  else parameter_product_d<3>(x, w, g_mu, g_lam);
}

void Solver::elastic_parameter_gradient(const Scalar* x, const Scalar* w, Scalar factor,
                                        ParameterGradient& params) const {
  const Index count = model_.element_count;
  std::vector<Scalar> g_mu(count), g_lam(count);
  parameter_product(x, w, g_mu.data(), g_lam.data());
  lame_to_parameters(g_mu, g_lam, factor, params);
}

void Solver::lame_to_parameters(const std::vector<Scalar>& g_mu, const std::vector<Scalar>& g_lam,
                                Scalar factor, ParameterGradient& params) const {
  const Parameters& p = model_.parameters;
  const Index count = model_.element_count;
  const bool uniform_E = p.youngs_modulus.size() == 1, uniform_nu = p.poisson_ratio.size() == 1;
  const auto chain = [&](Index e, Scalar& dE, Scalar& dnu) {
    const Scalar E = p.youngs_modulus[uniform_E ? 0 : e], nu = p.poisson_ratio[uniform_nu ? 0 : e];
    const Scalar a = 1 + nu, b = 1 - 2 * nu;
    const Scalar dmu_dE = 1 / (2 * a), dmu_dnu = -E / (2 * a * a);
    const Scalar dlam_dE = nu / (a * b), dlam_dnu = E * (1 + 2 * nu * nu) / (a * a * b * b);
    dE = factor * (g_mu[e] * dmu_dE + g_lam[e] * dlam_dE);
    dnu = factor * (g_mu[e] * dmu_dnu + g_lam[e] * dlam_dnu);
  };
  // A uniform value's gradient is the elements' sum (parallel_sum: the same bits on any thread
  // count), so a stored run and step-by-step calls add the same per-step values.
  params.youngs_modulus.assign(uniform_E ? 1 : count, 0);
  params.poisson_ratio.assign(uniform_nu ? 1 : count, 0);
  if (!uniform_E || !uniform_nu)
    parallel_for(count, [&](Index e) {
      Scalar dE, dnu;
      chain(e, dE, dnu);
      if (!uniform_E) params.youngs_modulus[e] = dE;
      if (!uniform_nu) params.poisson_ratio[e] = dnu;
    });
  if (uniform_E) params.youngs_modulus[0] = parallel_sum(count, [&](Index e) {
    Scalar dE, dnu;
    chain(e, dE, dnu);
    return dE;
  });
  if (uniform_nu) params.poisson_ratio[0] = parallel_sum(count, [&](Index e) {
    Scalar dE, dnu;
    chain(e, dE, dnu);
    return dnu;
  });
}

template <int D>
Scalar Solver::adjoint_elements_d(const Scalar* x, const Scalar* w, Scalar* Kw, Scalar* g_mu,
                                     Scalar* g_lam, bool work) {
  const Model& m = model_;
  // K w by the neo-Hookean tetrahedra's lane pass where it applies (whatever else is asked, so
  // that K w does not depend on which parameter gradients are wanted); the parameter terms in
  // a pass of their own then.
  const bool by_lanes = lanes::kAvailable && D == 3 && m.material() == Material::NeoHookean;
  if (by_lanes) lanes::neohookean_terms(m, lane_constants(), x, w, avx2_, element_vectors_.data());
  std::vector<Scalar> element_work(work ? m.element_count : 0);
  if (!by_lanes || g_mu || work)
    parallel_for(m.element_count, [&](Index e) {
      const Scalar work_e = element_adjoint_term<D>(m, x, w, e, by_lanes ? nullptr : element_vectors_.data(),
                                                    g_mu, g_lam, work);
      if (work) element_work[e] = work_e;
    });
  assembly_.gather_vector(element_vectors_.data(), Kw);
  return work ? parallel_sum(m.element_count, [&](Index e) { return element_work[e]; }) : 0;
}

void Solver::step_adjoint(const State& before, const State& after, Scalar dt,
                          const Scalar* control, State& adjoint, ParameterGradient& params,
                          Scalar* grad_control, Interrupt& interrupt,
                          const ParameterMask& wanted) {
  adjoint_step(before, after, after.factor.x.empty() ? before.factor : after.factor, dt, control,
               adjoint, params, grad_control, interrupt, wanted);
}

void Solver::adjoint_step(const State& before, const State& after, const FactorRecord& factor,
                          Scalar dt, const Scalar* control, State& adjoint,
                          ParameterGradient& params, Scalar* grad_control, Interrupt& interrupt,
                          const ParameterMask& wanted) {
  if (!(dt > 0) || !std::isfinite(dt))
    throw InvalidArgument("dt: expected a finite time step > 0 [s], got " + format_real(dt));
  const std::size_t size = model_.rest.size();
  for (const State* s : {&before, &after, static_cast<const State*>(&adjoint)})
    if (s->x.size() != size || s->v.size() != size)
      throw InvalidArgument("step_adjoint: every state must hold x and v of " +
                            std::to_string(model_.vertex_count) + " vertices");
  interrupt.check();
  if (config_.integrator == Integrator::Symplectic)
    adjoint_symplectic(before, after, dt, control, adjoint, params, grad_control, wanted);
  else
    adjoint_implicit(before, after, factor, dt, control, adjoint, params, grad_control, interrupt,
                     wanted);
}

void Solver::adjoint_symplectic(const State& before, const State& after, Scalar dt,
                                const Scalar* control, State& adjoint,
                                ParameterGradient& params, Scalar* grad_control,
                                const ParameterMask& wanted) {
  const Model& m = model_;
  const int d = m.dim;
  const Index n = assembly_.dof_count();
  const Scalar c = m.damping(), rho = m.parameters.density;
  const Scalar damp = 1 / (1 + dt * c);
  std::vector<Scalar>& w = adjoint_w_;
  std::vector<Scalar>& Kw = adjoint_kw_;
  w.resize(n);
  Kw.resize(n);
  // b + h a: dL/dv_{n+1} with x_{n+1} = x_n + h v_{n+1} folded in.
  parallel_for(m.vertex_count, [&](Index i) {
    for (int r = 0; r < d; ++r) {
      const Index q = i * d + r;
      w[q] = m.fixed[i] ? 0 : dt * damp / m.mass[i] * (adjoint.v[q] + dt * adjoint.x[q]);
    }
  });
  // One pass over the elements: K w, and (when wanted) w . df/d(mu, lam) and w . grad E.
  std::vector<Scalar> g_mu(wanted.elastic() ? m.element_count : 0), g_lam(g_mu.size());
  Scalar* gm = wanted.elastic() ? g_mu.data() : nullptr;
  Scalar* gl = wanted.elastic() ? g_lam.data() : nullptr;
  const Scalar w_grad_E = d == 2 ? adjoint_elements_d<2>(before.x.data(), w.data(), Kw.data(), gm, gl, wanted.density)
                                 : adjoint_elements_d<3>(before.x.data(), w.data(), Kw.data(), gm, gl, wanted.density);
  if (wanted.elastic()) lame_to_parameters(g_mu, g_lam, -1, params);  // f = -grad E
  // v_{n+1} = (v_n + h (f + u)/m) damp: d/drho of (f + u)/m with m = rho m^ is
  // -(f + u - m g)/(m rho) = -(u - grad E)/(m rho) (the gravity part m g does not depend on
  // rho); d/dc of damp is -h damp^2, so dv_{n+1}/dc = -h damp v_{n+1}. w is 0 on fixed dofs.
  if (wanted.density) {
    const Scalar w_u = control ? free_dof_sum(m, [&](Index, Index q, int) { return w[q] * control[q]; }) : 0;
    params.density = -(w_u - w_grad_E) / rho;
  }
  if (wanted.damping)
    params.damping = -free_dof_sum(m, [&](Index, Index q, int) {
      return (adjoint.v[q] + dt * adjoint.x[q]) * dt * damp * after.v[q];
    });
  parallel_for(m.vertex_count, [&](Index i) {
    for (int r = 0; r < d; ++r) {
      const Index q = i * d + r;
      const Scalar total_v = adjoint.v[q] + dt * adjoint.x[q];
      if (grad_control) grad_control[q] = w[q];
      adjoint.x[q] -= Kw[q];
      adjoint.v[q] = m.fixed[i] ? 0 : damp * total_v;
    }
  });
}

void Solver::adjoint_implicit(const State& before, const State& after,
                              const FactorRecord& factor, Scalar dt, const Scalar* control,
                              State& adjoint, ParameterGradient& params, Scalar* grad_control,
                              Interrupt& interrupt, const ParameterMask& wanted) {
  (void)control;  // G is linear in u: dG/du = -h^2 I whatever its value
  const Model& m = model_;
  const int d = m.dim;
  const Index n = assembly_.dof_count();
  const Scalar c = m.damping(), rho = m.parameters.density;
  const Scalar weight = 1 + dt * c, scale = dt * dt;
  const bool gravity = !m.gravity().empty();
  // H lambda = a + b/h on the free dofs (fixed rows: identity, zero right-hand side).
  std::vector<Scalar> rhs(n), lambda(n, 0);
  parallel_for(m.vertex_count, [&](Index i) {
    for (int r = 0; r < d; ++r) {
      const Index q = i * d + r;
      rhs[q] = m.fixed[i] ? 0 : adjoint.x[q] + adjoint.v[q] / dt;
    }
  });
  if (values_.empty()) values_.resize(assembly_.nonzeros());
  const CsrView A{n, n, assembly_.row_ptr().data(), assembly_.col_index().data(), values_.data()};
  // PCG preconditioned by the factor the forward step ended with (the State's record: the
  // projected Hessian of a nearby x, so a few iterations reach rounding), else, or when PCG
  // stalls, a factorisation of H. That factor is the forward solver's own when its record is
  // the forward's current one (read only: the forward's survives the backward pass); else the
  // adjoint rebuilds it into a factor of its own. Either is the same matrix's factor, so a
  // step's answer depends on its states only (not on which steps ran before it): checkpointed
  // and repeated backward passes agree bitwise.
  SpdSolveStats s;
  FactorRecord key = factor;
  key.refactor_pending = false;
  const bool lagged = config_.linear_solver != LinearSolver::CholmodDirect && !key.x.empty() &&
                      key.x.size() == after.x.size();
  const auto same_matrix = [&](const FactorRecord& r) {
    return r.x == key.x && r.weight == key.weight && r.scale == key.scale &&
           r.projected == key.projected;
  };
  SpdSolver* preconditioner = nullptr;
  if (lagged && spd_.has_factor() && same_matrix(factor_)) {
    preconditioner = &spd_;
  } else if (lagged) {
    if (!(adjoint_factor_ == key)) {
      assemble_newton_matrix(key.x.data(), key.weight, key.scale, key.projected);
      std::vector<Scalar> zero(n, 0), out(n);
      adjoint_factor_.x.clear();
      if (adjoint_spd_.solve_exact(A, zero.data(), out.data(), false, s)) adjoint_factor_ = key;
    }
    if (!adjoint_factor_.x.empty()) preconditioner = &adjoint_spd_;
  }
  assemble_newton_matrix(after.x.data(), weight, scale, false);
  bool ok = false;
  if (preconditioner) {
    const LinearOperator op = [&](const Scalar* v, Scalar* y) { spmv(A, v, y); };
    const LinearOperator pre = [&](const Scalar* r, Scalar* z) {
      preconditioner->solve_exact(A, r, z, true, s);
    };
    try {
      ok = pcg(n, op, pre, rhs.data(), lambda.data(), IterativeOptions{kAdjointTolerance, 50},
               interrupt).converged;
    } catch (const InvalidArgument&) {
      ok = false;  // negative curvature: H may be indefinite; the factorisation decides
    }
  }
  if (!ok) {
    std::fill(lambda.begin(), lambda.end(), 0);
    adjoint_factor_.x.clear();  // the factor becomes H's own, no record's
    ok = adjoint_spd_.solve_exact(A, rhs.data(), lambda.data(), false, s);
  }
  if (!ok)
    throw NotPositiveDefinite(
        "step_adjoint: the exact Hessian of the implicit step at its solution (step " +
            std::to_string(after.step) + ") is not positive definite: the solution is not a "
            "strict minimum and has no unique derivative; reduce dt",
        -1);

  if (wanted.elastic()) elastic_parameter_gradient(after.x.data(), lambda.data(), -scale, params);
  // dG/drho = (M/rho) ((x - y) + h c (x - x_n) - h^2 g) with y = x_n + h v_n; dG/dc = h M (x - x_n).
  if (wanted.density) params.density = -free_dof_sum(m, [&](Index i, Index q, int r) {
    const Scalar step = after.x[q] - before.x[q];
    const Scalar dG = (step - dt * before.v[q]) + dt * c * step - (gravity ? scale * m.gravity()[r] : 0);
    return lambda[q] * m.mass[i] / rho * dG;
  });
  if (wanted.damping) params.damping = -free_dof_sum(m, [&](Index i, Index q, int) {
    return lambda[q] * dt * m.mass[i] * (after.x[q] - before.x[q]);
  });
  std::vector<Scalar> K_lambda;
  if (m.fixed_count > 0) {
    K_lambda.resize(n);
    hessian_product(after.x.data(), lambda.data(), K_lambda.data());
  }
  parallel_for(m.vertex_count, [&](Index i) {
    for (int r = 0; r < d; ++r) {
      const Index q = i * d + r;
      if (m.fixed[i]) {
        if (grad_control) grad_control[q] = 0;
        adjoint.x[q] -= scale * K_lambda[q];
        adjoint.v[q] = 0;
      } else {
        if (grad_control) grad_control[q] = scale * lambda[q];
        adjoint.x[q] = weight * m.mass[i] * lambda[q] - adjoint.v[q] / dt;
        adjoint.v[q] = dt * m.mass[i] * lambda[q];
      }
    }
  });
}

}  // namespace kinema::fem
