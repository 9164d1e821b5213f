// The vector-Jacobian product of one mass-spring step (solver.h), for reverse-mode gradients.
// With lambda = dL/d(force) (explicit kinds) or the adjoint of the implicit solve, per spring
// (d = x_j - x_i, l = |d|, n = d / l, mu = lambda_j - lambda_i):
//   explicit, symplectic: v' = v + h M^-1 f(x, v), lambda = h M^-1 dL/dv'; the force's
//     adjoint is psi = -mu . f_i, differentiated in d, dv, k, L, c (kernels.h's f_i);
//   implicit: A(x) v' = b(x, v), A = M - h C - beta h^2 K, b = M v + h f; A lambda = dL/dv'
//     (A symmetric), then dL/dp = lambda . db/dp - lambda^T dA/dp v' for every input p: the
//     implicit function theorem, exact for the step as if its solve were exact (the adjoint
//     solve itself to Config::adjoint_tol, 1e-12 by default).
// Fixed vertices: v' = 0 and x' = x whatever the inputs, so their lambda is 0; their positions
// still enter the free vertices' forces and matrix rows.
#include <Eigen/Core>
#include <string>

#include "core/errors.h"
#include "core/parallel.h"
#include "massspring/kernels.h"
#include "massspring/spring_pass.h"
#include "massspring/solver.h"

namespace kinema::massspring {

namespace {

template <int D>
Vec<D> vertex(const Scalar* a, Index i) {
  return Eigen::Map<const Vec<D>>(a + i * D);
}

template <int D>
void put(Scalar* out, const Vec<D>& a) {
  for (int r = 0; r < D; ++r) {
    out[r] = a(r);
    out[D + r] = -a(r);
  }
}

// A scratch buffer of the solver, sized once (a backward pass calls this every step: fresh
// allocations of megabytes would cost page faults each time). Every entry is overwritten.
std::vector<Scalar>& scratch(std::vector<Scalar>& buffer, Index size) {
  buffer.resize(static_cast<std::size_t>(size));
  return buffer;
}

void check_adjoint_shapes(const Model& m, const State& before, const State& after,
                          const State& adjoint, const Params& p) {
  const std::size_t n = static_cast<std::size_t>(m.vertex_count * m.dim);
  const std::size_t sc = static_cast<std::size_t>(m.spring_count);
  const std::size_t vc = static_cast<std::size_t>(m.vertex_count);
  if (before.x.size() != n || before.v.size() != n || after.x.size() != n || after.v.size() != n)
    throw InvalidArgument("before, after: expected states of " + std::to_string(m.vertex_count) +
                          " vertices");
  if (adjoint.x.size() != n || adjoint.v.size() != n)
    throw InvalidArgument("grad_after: expected (n, d) arrays for x and v");
  const bool none = p.stiffness.empty() && p.rest_length.empty() && p.damping.empty() &&
                    p.mass.empty();
  if (!none && (p.stiffness.size() != sc || p.rest_length.size() != sc ||
                p.damping.size() != sc || p.mass.size() != vc))
    throw InvalidArgument("adjoint_params: expected arrays sized like the model's, or all empty");
}

bool wanted(const Params& p) { return !p.stiffness.empty(); }

}  // namespace

void Solver::run_adjoint(const std::vector<State>& states, Scalar dt, State& adjoint,
                         Params& params, Scalar* adjoint_controls, Interrupt& interrupt) {
  const Index steps = static_cast<Index>(states.size()) - 1;
  const Index n = assembly_.dof_count();
  for (Index k = steps - 1; k >= 0; --k)
    step_adjoint(states[k], states[k + 1], dt, adjoint, params,
                 adjoint_controls ? adjoint_controls + k * n : nullptr, interrupt);
}

void Solver::step_adjoint(const State& before, const State& after, Scalar dt, State& adjoint,
                          Params& params, Scalar* adjoint_control,
                          Interrupt& interrupt) {
  check_adjoint_shapes(model_, before, after, adjoint, params);
  interrupt.check();
  const int d = model_.dim;
  if (config_.integrator == Integrator::Implicit) {
    if (d == 2) adjoint_implicit_d<2>(before, after, dt, adjoint, params, adjoint_control);
    else adjoint_implicit_d<3>(before, after, dt, adjoint, params, adjoint_control);
  } else {
    if (d == 2) adjoint_explicit_d<2>(before, after, dt, adjoint, params, adjoint_control);
    else adjoint_explicit_d<3>(before, after, dt, adjoint, params, adjoint_control);
  }
}

template <int D>
void Solver::adjoint_explicit_d(const State& before, const State& after, Scalar dt, State& adjoint,
                                Params& params, Scalar* adjoint_control) {
  const Model& m = model_;
  const Index n = assembly_.dof_count();
  const bool symplectic = config_.integrator == Integrator::Symplectic;
  // The step's f / m, read back from its velocity change (free vertices): to rounding the same
  // as evaluating the forces again, at no cost.
  const Scalar* v_new = after.v.data();
  const Scalar* v_old = before.v.data();
  // lambda = dL/df = h M^-1 dL/dv'_total; dL/dv = dL/dv'_total (+ h dL/dx' for explicit Euler).
  Scalar* lambda = scratch(adj_lambda_, n).data();
  // dL/dx' is read and overwritten vertex by vertex (each reads only its own).
  Scalar* gx = adjoint.x.data();
  Scalar* gv = adjoint.v.data();
  const bool with_params = wanted(params);
  // One parallel region (spring_pass.h): each thread first makes lambda, dL/dv's own term and
  // the mass gradient of its vertices; after a barrier (the springs read their ends' lambda),
  // psi = -mu . f_i per spring in d (-> x), dv (-> v) and the parameters, each spring once,
  // signed into its ends' slots, and each vertex's sum of its slots in sequence (its springs in
  // spring order, as ElementAssembly's gather).
  const SpringInputs in = passes().inputs(before.x.data(), before.v.data());
  const Scalar* mass = m.mass.data();
  const unsigned char* fixed = m.fixed.data();
  Vec<D> g = Vec<D>::Zero();
  if (!m.gravity.empty()) g = Eigen::Map<const Vec<D>>(m.gravity.data());
  passes_.run<D, 2>(
      true,
      [&](Index begin, Index end, Scalar* out, bool owned) {
        const bool p = owned && with_params;
        spring_adjoint<D>(in, lambda, begin, end, avx2_, out, p ? params.stiffness.data() : nullptr,
                          params.rest_length.data(), params.damping.data());
      },
      [&, lambda, gx, gv, mass, fixed, v_new, v_old, g, adjoint_control](Index a, Index b) {
        for (Index i = a; i < b; ++i) {
          Eigen::Map<Vec<D>> li(lambda + i * D), gvi(gv + i * D);
          if (fixed[i]) {
            gvi.setZero();
            li.setZero();
          } else {
            const Eigen::Map<const Vec<D>> gxi(gx + i * D);
            const Vec<D> vbar = symplectic ? Vec<D>(gvi + dt * gxi) : Vec<D>(gvi);
            li = dt * vbar / mass[i];
            gvi = symplectic ? vbar : Vec<D>(vbar + dt * gxi);
            if (with_params) {
              const Vec<D> dv = (Eigen::Map<const Vec<D>>(v_new + i * D) -
                                 Eigen::Map<const Vec<D>>(v_old + i * D)) / dt;
              Scalar s = li(0) * (g(0) - dv(0));
              for (int r = 1; r < D; ++r) s += li(r) * (g(r) - dv(r));
              params.mass[i] += s;
            }
          }
          if (adjoint_control) Eigen::Map<Vec<D>>(adjoint_control + i * D) = li;
        }
      },
      [gx, gv](Index u, Index w, const Scalar* sum) {
        for (Index i = u; i < w; ++i) {
          Eigen::Map<Vec<D>>(gx + i * D) += Eigen::Map<const Vec<D>>(sum + (i - u) * 2 * D);
          // A fixed vertex's velocity still damps its springs (its own v' is 0 whatever v is).
          Eigen::Map<Vec<D>>(gv + i * D) += Eigen::Map<const Vec<D>>(sum + (i - u) * 2 * D + D);
        }
      });
}

template <int D>
void Solver::adjoint_implicit_d(const State& before, const State& after, Scalar dt, State& adjoint,
                                Params& params, Scalar* adjoint_control) {
  const Model& m = model_;
  const Index n = assembly_.dof_count();
  const Scalar beta = config_.beta;
  const bool clamp = after.clamped;
  // A lambda = dL/dv' + h dL/dx' (x' = x + h v'), zero on fixed rows.
  std::vector<Scalar>& rhs = scratch(adj_rhs_, n);
  std::vector<Scalar>& lambda = scratch(adj_lambda_, n);
  std::vector<Scalar>& gx = adj_gx_;
  gx = adjoint.x;
  parallel_for(m.vertex_count, [&](Index i) {
    for (int r = 0; r < D; ++r) {
      const Index q = i * D + r;
      rhs[q] = m.fixed[i] ? 0 : adjoint.v[q] + dt * gx[q];
      lambda[q] = 0;  // PCG's initial guess: the same every pass, so passes repeat exactly
    }
  });
  assemble(before.x.data(), dt, beta, clamp);
  SpdSolveStats stats;
  const bool new_pass = before.step >= adjoint_last_step_;
  adjoint_last_step_ = before.step;
  Interrupt none;  // the caller checks between steps
  const bool ok =
      config_.adjoint_tol > 0
          ? adjoint_linear_.solve(LinearSolver::Cholmod, matrix(), rhs.data(), lambda.data(),
                                  config_.adjoint_tol, !new_pass, none, stats)
          : adjoint_linear_.solve_exact(matrix(), rhs.data(), lambda.data(), false, stats);
  if (!ok)
    throw NotPositiveDefinite("step_adjoint: the implicit matrix of step " +
                              std::to_string(before.step) +
                              " is not positive definite, so the step has no unique derivative "
                              "(its forward solve converged on an indefinite matrix)", -1);
  const Scalar* vn = after.v.data();
  const Scalar* v = before.v.data();
  const bool with_params = wanted(params);
  // dL/dv = M lambda, dL/du = h lambda, dL/dm_i = lambda_i . (v_i + h g - v'_i) (free vertices).
  parallel_for(m.vertex_count, [&](Index i) {
    Scalar s = 0;
    for (int r = 0; r < D; ++r) {
      const Index q = i * D + r;
      const Scalar g = m.gravity.empty() ? 0 : m.gravity[r];
      adjoint.v[q] = m.mass[i] * lambda[q];
      if (adjoint_control) adjoint_control[q] = dt * lambda[q];
      s += lambda[q] * (v[q] + dt * g - vn[q]);
    }
    if (with_params) params.mass[i] += s;
  });
  // Per spring: lambda . h df/d(.) (the right-hand side's exact force) minus
  // d/d(.) [mu^T B w], B = beta h^2 k S + h c n n^T the spring's block of A, w = v'_j - v'_i.
  std::vector<Scalar>& ex = scratch(adj_ex_, m.spring_count * 2 * D);
  const Scalar* x = before.x.data();
  parallel_for(m.spring_count, [&](Index s) {
    const Index i = m.springs[2 * s], j = m.springs[2 * s + 1];
    const Vec<D> dd = vertex<D>(x, j) - vertex<D>(x, i);
    const Vec<D> mu = vertex<D>(lambda.data(), j) - vertex<D>(lambda.data(), i);
    const Vec<D> w = vertex<D>(vn, j) - vertex<D>(vn, i);
    const Scalar l = dd.norm();
    const Scalar k = m.stiffness[s], L = m.rest_length[s], c = m.damping[s];
    Vec<D> gi = Vec<D>::Zero();  // dL/dx_i of this spring (dL/dx_j = -gi)
    if (l > 0) {
      const Vec<D> nv = dd / l;
      const Scalar mn = mu.dot(nv), wn = w.dot(nv);
      const Mat<D> S = spring_jacobian<D>(dd, L, false);
      const Mat<D> Sc = spring_jacobian<D>(dd, L, clamp);
      const Scalar bh = beta * dt * dt;
      gi = dt * k * (S * mu) + bh * k * spring_jacobian_vjp<D>(dd, L, clamp, mu, w) +
           dt * c * spring_damping_vjp<D>(dd, mu, w);
      if (with_params) {
        params.stiffness[s] += -dt * (l - L) * mn - bh * mu.dot(Sc * w);
        params.rest_length[s] += dt * k * mn - bh * k * spring_jacobian_dL<D>(dd, L, clamp, mu, w);
        params.damping[s] += -dt * mn * wn;
      }
    }
    put<D>(ex.data() + s * 2 * D, gi);
  });
  std::vector<Scalar>& sum = scratch(adj_sum_, n);
  assembly_.gather_vector(ex.data(), sum.data());
  parallel_for(n, [&](Index q) { adjoint.x[q] = gx[q] + sum[q]; });
}

}  // namespace kinema::massspring
