// Mass-spring systems in 2D and 3D: Hooke springs with per-spring stiffness, rest length and
// damping, lumped vertex masses, fixed vertices and gravity (config / model / state / solver).
// Integrators, with f = f(x_n, v_n) + M g + u (u: the step's control forces) and K = df/dx,
// C = df/dv (kernels.h):
//   explicit Euler:    x' = x + h v,  v' = v + h M^-1 f
//   symplectic Euler:  v' = v + h M^-1 f,  x' = x + h v'
//   implicit:          [M - h C - beta h^2 K] v' = M v + h f_spring+gravity+control(x_n),  x' = x + h v'
// the last the unified form of Baraff & Witkin 1998 (eq. 18 rewritten for v'): beta = 1 is
// backward Euler linearised once, beta = 1/2 trapezoid-like. The matrix is assembled into a
// pattern fixed at construction and solved by linalg/spd_solver.h, whose CHOLMOD analysis is
// reused every step. step_adjoint is the vector-Jacobian product of one step (adjoint.cpp).
#pragma once

#include <vector>

#include "core/interrupt.h"
#include "core/simd.h"
#include "core/step_stats.h"
#include "linalg/spd_solver.h"
#include "massspring/spring_pass.h"
#include "mesh/element_assembly.h"

namespace kinema::massspring {

enum class Integrator { Explicit, Symplectic, Implicit };

struct Config {
  Integrator integrator = Integrator::Implicit;
  Scalar beta = 1;  // implicit weight of the stiffness term: 1 backward Euler, 1/2 trapezoid-like
  LinearSolver linear_solver = LinearSolver::Cholmod;
  Scalar cg_tol = 1e-8;  // relative residual of the (P)CG solves
  // Relative residual of step_adjoint's implicit solve, by PCG preconditioned with a CHOLMOD
  // factor lagged across the backward pass's steps (refactorised as the forward's is); 0: a
  // fresh factorisation every step. The forward's cg_tol is not what the gradient sees: the
  // step is differentiated as if solved exactly, to this tolerance.
  Scalar adjoint_tol = 1e-12;
};

// Throws InvalidArgument naming the field (beta >= 0 finite, cg_tol > 0 finite).
void check_config(const Config& config);

struct Model {
  int dim = 0;
  Index vertex_count = 0, spring_count = 0;
  std::vector<Index> springs;        // (m, 2)
  std::vector<Scalar> stiffness;     // (m,) [N/m]
  std::vector<Scalar> rest_length;   // (m,) [m]
  std::vector<Scalar> damping;       // (m,) [N s/m], along the spring
  std::vector<Scalar> mass;          // (n,) [kg]
  std::vector<unsigned char> fixed;  // (n,)
  std::vector<Scalar> gravity;       // (d,) or empty (no gravity pass)
};

// Validates and builds; scalars are broadcast by the caller (arrays of full length here).
Model make_model(int dim, Index vertex_count, const Index* springs, Index spring_count,
                 const Scalar* stiffness, const Scalar* rest_length, const Scalar* damping,
                 const Scalar* mass, const Index* fixed, Index fixed_count,
                 const std::vector<Scalar>& gravity);

// The per-item parameters' values checked as make_model checks them (after an update).
void check_parameters(const Model& model);

// The lagged CHOLMOD factor an implicit step preconditions with is history the step reads: the
// State records the matrix it is the factor of (the positions, dt, beta and branch it was
// assembled with), so that a solver handed a copied State rebuilds that factor bit for bit.
struct FactorRecord {
  bool valid = false;          // a factor exists (else the next solve factorises)
  bool refactor_next = false;  // the last PCG was slow: the next solve factorises
  bool clamped = false;
  Scalar dt = 0, beta = 0;
  std::vector<Scalar> x;  // (n, d) [m]; empty when not valid
  bool operator==(const FactorRecord& o) const {
    return valid == o.valid && refactor_next == o.refactor_next && clamped == o.clamped &&
           dt == o.dt && beta == o.beta && x == o.x;
  }
};

struct State {
  std::vector<Scalar> x, v;  // (n, d) [m], [m/s]
  Scalar time = 0;           // [s]
  Index step = 0;
  bool clamped = false;  // the last implicit step used the clamped Jacobian (its adjoint does too)
  FactorRecord factor;
};

// Stability of the explicit and symplectic steps, linearised at rest (the module docstring of
// python/kinema/massspring.py): omega_max^2 of M^-1 K and the damping rate of M^-1 C bounded
// above by Gershgorin's theorem (per free vertex, the sums of 2 k / m and 2 c / m over its
// springs), and bounded below by a Rayleigh quotient.
struct ExplicitLimits {
  Scalar omega2 = 0;  // Gershgorin's bound of omega_max^2 [1/s^2]
  Scalar gamma = 0;   // Gershgorin's bound of the damping rate [1/s]
  // The root of h^2 omega2 + 2 h gamma = 4 (2 / sqrt(omega2) undamped; infinity when nothing is
  // stiff or damped): every step below it is stable.
  Scalar dt_limit = 0;
  // 2 / omega with omega^2 the largest Rayleigh quotient of one spring's own stretching mode
  // (4 k / (m_i + m_j), or k / m of the free end of a spring to a fixed vertex), a lower bound
  // of omega_max^2 (infinity without a stiff spring to a free vertex): every step above it is
  // unstable.
  Scalar unstable_dt = 0;
};

struct StepStats : StepStatsBase {
  bool clamped = false;     // the exact Jacobian was not definite; the clamped one was used
  bool refactored = false;  // a CHOLMOD factorisation was computed in this step
  Index factorizations = 0;
  Index cg_iterations = 0;
  double seconds_assembly = 0, seconds_factor = 0, seconds_solve = 0;
};

// Gradients with respect to the model's per-item parameters (the shapes of Model's arrays).
struct Params {
  std::vector<Scalar> stiffness, rest_length, damping, mass;
};

class Solver {
 public:
  Solver(const Model& model, const Config& config);

  const Model& model() const { return model_; }
  Config& config() { return config_; }
  State initial_state(const Scalar* x0) const;

  // control: n d forces [N] added where gravity is (fixed vertices ignore them), or null.
  StepStats step(State& state, Scalar dt, Interrupt& interrupt, const Scalar* control = nullptr);
  // The same step from `before` into `after` (resized; its buffers reused, no copy of the new
  // x and v): what a stored run takes. `after` must not be `before`.
  StepStats step(const State& before, State& after, Scalar dt, Interrupt& interrupt,
                 const Scalar* control = nullptr);

  // Vector-Jacobian product of step(before, dt, control) -> after. On entry adjoint.x, adjoint.v
  // hold dL/dx', dL/dv'; on exit dL/dx, dL/dv of `before`. dL/d(parameters) of this step are
  // added to adjoint_params (sized like the model's arrays), dL/du written to adjoint_control
  // (n d, when not null). The control's value is not needed: forces enter the step linearly. The implicit step is differentiated as if solved exactly (implicit
  // function theorem: one solve with the step's matrix to Config::adjoint_tol), on the branch
  // the step took (after.clamped).
  // adjoint_params with every array empty: no parameter gradient is wanted (none is computed).
  void step_adjoint(const State& before, const State& after, Scalar dt, State& adjoint,
                    Params& adjoint_params, Scalar* adjoint_control, Interrupt& interrupt);

  // step_adjoint over a stored run, last step first, without a round trip per step: states[k]
  // is the state before step k (k = 0..T; states[T] the end; the controls' values are not
  // needed: forces enter every step linearly). adjoint: dL/d(states[T]) on entry, dL/d(states[0]) on exit; adjoint_params accumulates the
  // steps' gradients (per item, last step first: the sums a caller adding step by step forms);
  // adjoint_controls (T n d, or null) receives each step's dL/du.
  void run_adjoint(const std::vector<State>& states, Scalar dt, State& adjoint,
                   Params& adjoint_params, Scalar* adjoint_controls, Interrupt& interrupt);

  // The model's parameters were changed in place: cached matrices and limits are stale.
  void model_changed() {
    factor_known_ = false;
    passes_stale_ = true;
    limits_known_ = false;
  }

  Scalar kinetic_energy(const State& s) const;
  Scalar spring_energy(const State& s) const;
  Scalar gravity_energy(const State& s) const;
  // f(x, v): springs, damping and gravity, every vertex.
  void forces(const State& s, Scalar* f);
  // The explicit and symplectic steps' stability bounds for the model's current parameters:
  // one O(springs) pass, then cached until model_changed() (each step's check reads them).
  const ExplicitLimits& explicit_limits() const;
  Scalar explicit_dt_limit() const { return explicit_limits().dt_limit; }

 private:
  template <int D> void forces_d(const State& s, const Scalar* control, bool with_damping, Scalar* f);
  // The explicit and symplectic steps into x_out, v_out (not s's), in one pass over the springs
  // and vertices (spring_pass.h). False when a v' or x' is not finite.
  template <int D> bool explicit_step_d(const State& s, Scalar dt, const Scalar* control,
                                        Scalar* x_out, Scalar* v_out);
  // explicit_step_d into x_out, v_out (sized); throws DivergenceError naming the first
  // non-finite quantity.
  void explicit_step(const State& before, Scalar dt, const Scalar* control,
                     std::vector<Scalar>& x_out, std::vector<Scalar>& v_out);
  // The spring passes with the model's current parameters.
  SpringPasses& passes();
  template <int D> void assemble_d(const Scalar* x, Scalar dt, Scalar beta, bool clamp);
  void assemble(const Scalar* x, Scalar dt, Scalar beta, bool clamp);
  CsrView matrix() const;
  void sync_factor(const State& state);
  void record_solve(FactorRecord& record, const State& state, Scalar dt, bool clamp, bool ok,
                    const SpdSolveStats& s) const;
  template <int D> void adjoint_explicit_d(const State& before, const State& after, Scalar dt,
                                           State& adjoint, Params& params, Scalar* adjoint_control);
  template <int D> void adjoint_implicit_d(const State& before, const State& after, Scalar dt,
                                           State& adjoint, Params& params, Scalar* adjoint_control);
  void check_finite(const std::vector<Scalar>& a, const char* quantity, Index step) const;

  const Model& model_;
  Config config_;
  ElementAssembly assembly_;
  std::vector<Scalar> element_vectors_, element_matrices_, values_, f_, rhs_, x_new_, v_new_;
  // The explicit kinds' spring passes: each vertex sums its springs' terms in the model's
  // spring order, the order ElementAssembly::gather_vector sums a vertex's contributions in, so
  // the passes give the bits of forces_d + gather.
  SpringPasses passes_;
  bool passes_stale_ = true;  // the model's parameters changed since passes_ copied them
  SpdSolver linear_;
  SpdSolver adjoint_linear_;  // its own factor, so a backward pass leaves the forward's alone
  // The step index of the last adjoint: a backward pass visits steps in decreasing order, so
  // an index not below it starts a new pass, which starts from a fresh factor. Every pass then
  // sees the same sequence of matrices and gives the same gradients bit for bit (stored,
  // checkpointed, chained or repeated).
  Index adjoint_last_step_ = -1;
  std::vector<Scalar> adj_lambda_, adj_gx_, adj_rhs_, adj_ex_, adj_sum_;  // step_adjoint's
  bool avx2_ = use_avx2();             // the 2D spring passes' AVX2 version (core/simd.h)
  FactorRecord factor_;       // what linear_'s lagged factor is (valid while factor_known_)
  bool factor_known_ = true;
  mutable ExplicitLimits limits_;     // explicit_limits(), valid while limits_known_
  mutable bool limits_known_ = false;
};

}  // namespace kinema::massspring
