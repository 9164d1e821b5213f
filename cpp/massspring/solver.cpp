#include "massspring/solver.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <string>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/timer.h"
#include "massspring/kernels.h"
#include "massspring/spring_pass.h"
#include "mesh/vertex_set.h"

namespace kinema::massspring {

namespace {

template <int D>
Vec<D> vertex(const Scalar* a, Index i) {
  return Eigen::Map<const Vec<D>>(a + i * D);
}

// Schemes divide by dt^2 (the implicit matrix's scale): below this dt makes them overflow.
constexpr Scalar kMinTimeStep = 1e-150;

void check_dt(Scalar dt) {
  if (!(std::isfinite(dt) && dt > 0))
    throw InvalidArgument("dt: expected a finite number > 0, got " + format_real(dt));
  if (dt < kMinTimeStep)
    throw InvalidArgument("dt: " + format_real(dt) +
                          " is below 1e-150: 1/dt^2 would overflow float64; choose other units");
}

// LaggedCholesky's rule (linalg/lagged_cholesky.h) with SpdSolver's PCG cap of 25: a PCG solve
// of more than 25 / 2 iterations makes the next solve factorise.
constexpr Index kSlowPcg = 25 / 2;

}  // namespace

Solver::Solver(const Model& model, const Config& config)
    : model_(model),
      config_(config),
      assembly_(model.vertex_count, model.dim, 2, model.springs.data(), model.spring_count) {
  check_config(config_);
  element_vectors_.resize(model_.spring_count * assembly_.element_vector_size());
  f_.resize(assembly_.dof_count());
  passes_.build(model_.springs.data(), model_.spring_count, model_.vertex_count, model_.dim);
}

SpringPasses& Solver::passes() {
  if (passes_stale_) {
    passes_.set_parameters(model_.stiffness.data(), model_.rest_length.data(), model_.damping.data());
    passes_stale_ = false;
  }
  return passes_;
}

State Solver::initial_state(const Scalar* x0) const {
  State s;
  const Index n = assembly_.dof_count();
  s.x.assign(x0, x0 + n);
  s.v.assign(n, 0);
  return s;
}

// ---------------------------------------------------------------- energies, forces

Scalar Solver::kinetic_energy(const State& s) const {
  return lumped_kinetic_energy(model_.mass.data(), s.v.data(), model_.vertex_count, model_.dim);
}

Scalar Solver::spring_energy(const State& s) const {
  const int d = model_.dim;
  const auto& x = s.x;
  return parallel_sum(model_.spring_count, [&](Index e) {
    const Index i = model_.springs[2 * e], j = model_.springs[2 * e + 1];
    Scalar l2 = 0;
    for (int r = 0; r < d; ++r) l2 += (x[j * d + r] - x[i * d + r]) * (x[j * d + r] - x[i * d + r]);
    const Scalar dl = std::sqrt(l2) - model_.rest_length[e];
    return model_.stiffness[e] / 2 * dl * dl;
  });
}

Scalar Solver::gravity_energy(const State& s) const {
  if (model_.gravity.empty()) return 0;
  const int d = model_.dim;
  return parallel_sum(model_.vertex_count, [&](Index i) {
    Scalar gx = 0;
    for (int r = 0; r < d; ++r) gx += model_.gravity[r] * s.x[i * d + r];
    return -model_.mass[i] * gx;
  });
}

template <int D>
void Solver::forces_d(const State& st, const Scalar* control, bool with_damping, Scalar* f) {
  const Model& m = model_;
  const Scalar* x = st.x.data();
  const Scalar* v = st.v.data();
  parallel_for(m.spring_count, [&](Index s) {
    const Index i = m.springs[2 * s], j = m.springs[2 * s + 1];
    const Vec<D> d = vertex<D>(x, j) - vertex<D>(x, i);
    const Vec<D> dv = vertex<D>(v, j) - vertex<D>(v, i);
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
  if (control)
    parallel_for(m.vertex_count * D, [&](Index q) { f[q] += control[q]; });
}

template <int D>
bool Solver::explicit_step_d(const State& st, Scalar dt, const Scalar* control, Scalar* x_out,
                             Scalar* v_out) {
  const Model& m = model_;
  const Scalar* x = st.x.data();
  const Scalar* v = st.v.data();
  const Scalar* mass = m.mass.data();
  const unsigned char* fixed = m.fixed.data();
  const bool symplectic = config_.integrator == Integrator::Symplectic;
  Vec<D> g = Vec<D>::Zero();
  if (!m.gravity.empty()) g = Eigen::Map<const Vec<D>>(m.gravity.data());
  const bool gravity = !m.gravity.empty();
  // f(x_n, v_n): each spring's force once, then per vertex the sum of its springs' in spring
  // order (as forces_d + gather, term for term) and the update of its x and v, in one pass
  // (spring_pass.h); explicit Euler moves x with v_n, symplectic Euler with v_{n+1}.
  const SpringInputs in = passes().inputs(x, v);
  std::atomic<bool> finite{true};  // every free vertex's v' and x' (no re-read)
  passes_.run<D, 1>(
      false,
      [&](Index begin, Index end, Scalar* out, bool) { spring_forces<D>(in, begin, end, avx2_, out); },
      [](Index, Index) {},
      [&, x, v, mass, fixed, x_out, v_out, control, g](Index u, Index w, const Scalar* f) {
        // x' - x' is 0 for a finite x', NaN otherwise: one test per block.
        Vec<D> check = Vec<D>::Zero();
        for (Index i = u; i < w; ++i) {
          const Eigen::Map<const Vec<D>> xi(x + i * D), vi(v + i * D);
          Eigen::Map<Vec<D>> xo(x_out + i * D), vo(v_out + i * D);
          if (fixed[i]) {
            xo = xi;
            vo.setZero();
            continue;
          }
          Vec<D> fi = Eigen::Map<const Vec<D>>(f + (i - u) * D);
          if (gravity) fi += mass[i] * g;
          if (control) fi += Eigen::Map<const Vec<D>>(control + i * D);
          const Vec<D> vq = vi + dt * fi / mass[i];
          xo = xi + dt * (symplectic ? vq : Vec<D>(vi));
          vo = vq;
          check += (vq - vq) + (xo - xo);
        }
        if (!check.allFinite()) finite.store(false, std::memory_order_relaxed);
      });
  return finite;
}

void Solver::forces(const State& s, Scalar* f) {
  if (model_.dim == 2) forces_d<2>(s, nullptr, true, f);
  else forces_d<3>(s, nullptr, true, f);
}

const ExplicitLimits& Solver::explicit_limits() const {
  if (limits_known_) return limits_;
  const Model& m = model_;
  const Scalar inf = std::numeric_limits<Scalar>::infinity();
  // Gershgorin's row sums of M^-1 K and M^-1 C at rest, each vertex's in spring order.
  std::vector<Scalar> stiff(m.vertex_count, 0), damp(m.vertex_count, 0);
  Scalar top = 0;  // the largest Rayleigh quotient of one spring's stretching mode
  for (Index s = 0; s < m.spring_count; ++s) {
    const Index i = m.springs[2 * s], j = m.springs[2 * s + 1];
    const Scalar k = m.stiffness[s];
    for (const Index a : {i, j}) {
      stiff[a] += 2 * k;
      damp[a] += 2 * m.damping[s];
    }
    const bool free_i = !m.fixed[i], free_j = !m.fixed[j];
    if ((free_i || free_j) && k > 0)
      top = std::max(top, (free_i && free_j ? 4 * k : k) / ((free_i ? m.mass[i] : 0) + (free_j ? m.mass[j] : 0)));
  }
  ExplicitLimits out;
  for (Index i = 0; i < m.vertex_count; ++i)
    if (!m.fixed[i]) {
      out.omega2 = std::max(out.omega2, stiff[i] / m.mass[i]);
      out.gamma = std::max(out.gamma, damp[i] / m.mass[i]);
    }
  // h^2 omega2 + 2 h gamma = 4 solved without cancellation.
  const Scalar g = out.gamma;
  out.dt_limit = g > 0 || out.omega2 > 0 ? 4 / (g + std::sqrt(g * g + 4 * out.omega2)) : inf;
  out.unstable_dt = top > 0 ? 2 / std::sqrt(top) : inf;
  limits_ = out;
  limits_known_ = true;
  return limits_;
}

void Solver::check_finite(const std::vector<Scalar>& a, const char* quantity, Index step) const {
  for (Scalar v : a)
    if (!std::isfinite(v))
      throw DivergenceError(std::string(quantity) + ": non-finite value at step " +
                            std::to_string(step) + "; the explicit limit is about dt < " +
                            format_real(explicit_dt_limit()) + " s: reduce dt or use integrator='implicit'");
}

// ---------------------------------------------------------------- implicit matrix

// values = M - h C - beta h^2 K at positions x, fixed rows/columns replaced by m_i I.
template <int D>
void Solver::assemble_d(const Scalar* x, Scalar dt, Scalar beta, bool clamp) {
  const Model& m = model_;
  constexpr int K = 2 * D;
  if (element_matrices_.empty()) element_matrices_.resize(m.spring_count * K * K);
  if (values_.empty()) values_.resize(assembly_.nonzeros());
  parallel_for(m.spring_count, [&](Index s) {
    const Index i = m.springs[2 * s], j = m.springs[2 * s + 1];
    const Vec<D> d = vertex<D>(x, j) - vertex<D>(x, i);
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

void Solver::assemble(const Scalar* x, Scalar dt, Scalar beta, bool clamp) {
  if (model_.dim == 2) assemble_d<2>(x, dt, beta, clamp);
  else assemble_d<3>(x, dt, beta, clamp);
}

CsrView Solver::matrix() const {
  const Index n = assembly_.dof_count();
  return CsrView{n, n, assembly_.row_ptr().data(), assembly_.col_index().data(), values_.data()};
}

// Makes linear_'s lagged factor the one state.factor records (when it is not already).
void Solver::sync_factor(const State& state) {
  if (factor_known_ && factor_ == state.factor) return;
  const FactorRecord& r = state.factor;
  if (r.valid && !r.refactor_next) {
    assemble(r.x.data(), r.dt, r.beta, r.clamped);
    std::vector<Scalar> zero(assembly_.dof_count(), 0), out(zero.size());
    SpdSolveStats s;
    if (!linear_.solve_exact(matrix(), zero.data(), out.data(), false, s))
      throw InvalidArgument("state: its lagged factor's matrix is not positive definite for this "
                            "system (a state of another system?)");
  }
  factor_ = r;
  factor_known_ = true;
}

// What a solve did to linear_'s lagged factor, as LaggedCholesky decides it.
void Solver::record_solve(FactorRecord& r, const State& state, Scalar dt, bool clamp, bool ok,
                          const SpdSolveStats& s) const {
  if (s.factorizations > 0) {
    r.refactor_next = false;
    r.valid = ok;
    if (ok) {
      r.x = state.x;
      r.dt = dt;
      r.beta = config_.beta;
      r.clamped = clamp;
    } else {
      r.x.clear();
    }
  } else if (ok) {
    r.refactor_next = s.cg_iterations > kSlowPcg;
  }
}

// ---------------------------------------------------------------- step

StepStats Solver::step(State& state, Scalar dt, Interrupt& interrupt, const Scalar* control) {
  check_dt(dt);
  check_config(config_);
  Stopwatch clock, phase;
  StepStats stats;
  const Model& m = model_;
  const int d = m.dim;
  const Index n = assembly_.dof_count();
  if (config_.integrator != Integrator::Implicit) {
    x_new_.resize(state.x.size());
    v_new_.resize(state.v.size());
    explicit_step(state, dt, control, x_new_, v_new_);
    accept_step(state, x_new_, v_new_, dt);
    state.clamped = false;
    stats.time = state.time;
    stats.dt = dt;
    stats.seconds = clock.seconds();
    return stats;
  }
  std::vector<Scalar> x = state.x, v = state.v;
  bool clamped = false;
  {
    // Elastic, gravity and control forces at x_n; damping enters the matrix, implicitly in v'.
    if (d == 2) forces_d<2>(state, control, false, f_.data());
    else forces_d<3>(state, control, false, f_.data());
    rhs_.resize(n);
    parallel_for(m.vertex_count, [&](Index i) {
      for (int r = 0; r < d; ++r) {
        const Index q = i * d + r;
        rhs_[q] = m.fixed[i] ? 0 : m.mass[i] * v[q] + dt * f_[q];  // M v + h f
      }
    });
    interrupt.check();
    const LinearSolver kind = config_.linear_solver;
    // The lagged kinds read the factor of an earlier step: the one state.factor records. Every
    // CHOLMOD kind leaves a factor behind, recorded in the state for the next step.
    const bool cholmod = kind != LinearSolver::CG;
    if (kind == LinearSolver::Cholmod || kind == LinearSolver::CholmodPcg) sync_factor(state);
    // A factor the record says is stale (or absent) is refactorised first, as it was originally.
    const bool reuse = !factor_.refactor_next && factor_.valid;
    FactorRecord record = factor_;
    if (cholmod) factor_known_ = false;  // until the solves below are recorded
    // [M - h C - beta h^2 K] v' = M v + h f with the exact spring Jacobian; when it is not
    // positive definite (springs compressed far below rest length), the clamped one.
    for (int attempt = 0; attempt < 2; ++attempt) {
      const bool clamp = attempt == 1;
      clamped = clamp;
      phase.restart();
      assemble(state.x.data(), dt, config_.beta, clamp);
      stats.seconds_assembly += phase.seconds();
      if (kind == LinearSolver::CG) std::fill(v.begin(), v.end(), 0);  // PCG starts from v' = v
      SpdSolveStats s;
      bool ok = false;
      try {
        ok = linear_.solve(kind, matrix(), rhs_.data(), v.data(), config_.cg_tol,
                           reuse || attempt > 0, interrupt, s);
      } catch (const InvalidArgument&) {
        // CG's certificates of indefiniteness (a diagonal entry or a curvature p^T A p <= 0):
        // the exact matrix goes the way of a failed factorisation, to the clamped one.
        if (kind != LinearSolver::CG || clamp) throw;
        s.converged = false;
      }
      stats.cg_iterations += s.cg_iterations;
      stats.factorizations += s.factorizations;
      stats.seconds_factor += s.seconds_factor;
      stats.seconds_solve += s.seconds_solve;
      if (cholmod) record_solve(record, state, dt, clamp, ok, s);
      if (kind == LinearSolver::CG) {
        if (s.converged) break;
        if (clamp)
          throw ConvergenceError("implicit step: CG reached " + std::to_string(s.cg_iterations) +
                                 " iterations at step " + std::to_string(state.step) +
                                 "; use linear_solver='cholmod' or reduce dt");
        continue;
      }
      if (ok) break;
      if (clamp)
        throw NotPositiveDefinite("implicit step: the clamped implicit matrix is not positive "
                                  "definite at step " + std::to_string(state.step) +
                                  "; check for negative stiffness or reduce dt", -1);
    }
    stats.refactored = stats.factorizations > 0;
    if (cholmod) {
      factor_ = record;
      factor_known_ = true;
    }
    // x' = x + h v'
    parallel_for(n, [&](Index q) { x[q] += dt * v[q]; });
  }
  check_finite(v, "v", state.step);
  check_finite(x, "x", state.step);
  accept_step(state, x, v, dt);
  state.clamped = clamped;
  if (config_.integrator == Integrator::Implicit && config_.linear_solver != LinearSolver::CG)
    state.factor = factor_;
  stats.clamped = clamped;
  stats.time = state.time;
  stats.dt = dt;
  stats.seconds = clock.seconds();
  return stats;
}

StepStats Solver::step(const State& before, State& after, Scalar dt, Interrupt& interrupt,
                       const Scalar* control) {
  if (config_.integrator == Integrator::Implicit) {
    after = before;
    return step(after, dt, interrupt, control);
  }
  check_dt(dt);
  check_config(config_);
  Stopwatch clock;
  after.x.resize(before.x.size());
  after.v.resize(before.v.size());
  explicit_step(before, dt, control, after.x, after.v);
  after.time = before.time + dt;  // accept_step's arithmetic
  after.step = before.step + 1;
  after.clamped = false;
  after.factor = before.factor;
  StepStats stats;
  stats.time = after.time;
  stats.dt = dt;
  stats.seconds = clock.seconds();
  return stats;
}

void Solver::explicit_step(const State& before, Scalar dt, const Scalar* control,
                           std::vector<Scalar>& x_out, std::vector<Scalar>& v_out) {
  const bool finite = model_.dim == 2
                          ? explicit_step_d<2>(before, dt, control, x_out.data(), v_out.data())
                          : explicit_step_d<3>(before, dt, control, x_out.data(), v_out.data());
  if (!finite) {  // the message names the first non-finite quantity
    check_finite(v_out, "v", before.step);
    check_finite(x_out, "x", before.step);
  }
}

// adjoint.cpp evaluates the same forces.
template void Solver::forces_d<2>(const State&, const Scalar*, bool, Scalar*);
template void Solver::forces_d<3>(const State&, const Scalar*, bool, Scalar*);

}  // namespace kinema::massspring
