// The time step of an elastic body (fem/model.h) and its adjoint.
// Implicit Euler is the minimisation of the incremental potential
//   g(x) = 1/2 ||x - (x_n + h v_n)||_M^2 + h c/2 ||x - x_n||_M^2 + h^2 (E(x) - (M g + u) . x),
// x_{n+1} = argmin g, v_{n+1} = (x_{n+1} - x_n)/h (Martin et al., "Example-based elastic
// materials", 2011; Gast et al., "Optimization integrator for large time steps", 2015), solved by
// projected Newton (element Hessians made positive semidefinite) with a backtracking (Armijo)
// line search, converged on the gradient norm relative to its value at the inertial guess.
// Symplectic Euler: v_{n+1} = (v_n + h M^-1 f(x_n)) / (1 + h c), x_{n+1} = x_n + h v_{n+1}.
// c is a mass-proportional (Rayleigh) damping rate [1/s]; u the step's control forces [N]
// (none on fixed vertices, which keep their positions and have v = 0).
// The adjoint step is the vector-Jacobian product of either step (fem/adjoint.cpp); the
// implicit one by the implicit function theorem on grad g(x_{n+1}) = 0 with the exact Hessian,
// solved to rounding by PCG with the forward step's own CHOLMOD factor, or by a factorisation.
#pragma once

#include <vector>

#include "core/interrupt.h"
#include "core/simd.h"
#include "core/step_stats.h"
#include "fem/model.h"
#include "fem/neohookean_lanes.h"
#include "linalg/spd_solver.h"
#include "mesh/element_assembly.h"

namespace kinema::fem {

// A symplectic step fills the base only.
struct StepStats : StepStatsBase {
  Index iterations = 0;               // Newton iterations
  bool converged = false;             // ||grad g|| <= tol ||grad g(x0)|| (symplectic: true)
  std::vector<Scalar> gradient_norm;  // ||grad g|| at each iterate (absolute)
  std::vector<Scalar> step_length;    // accepted line-search step per iteration
  Index projected_elements = 0;       // elements whose dP/dF was clamped (last iteration)
  Index cg_iterations = 0;
  Index factorizations = 0;           // CHOLMOD numeric factorisations
  double seconds_assembly = 0, seconds_factor = 0, seconds_solve = 0, seconds_line_search = 0;
};

// dL/d(parameters) of one adjoint step (or of a stored run's steps, summed), per element for
// youngs_modulus and poisson_ratio, or one value (the elements' sum, in a fixed order) where the
// model holds a uniform value.
struct ParameterGradient {
  std::vector<Scalar> youngs_modulus, poisson_ratio;  // (m,) or (1,) [1/Pa], [1]
  Scalar density = 0;                                 // [m^d/kg]
  Scalar damping = 0;                                 // [s]
};

// Which parameter gradients an adjoint step computes (the rest stay empty / zero): a gradient
// nobody asked for costs element passes.
struct ParameterMask {
  bool youngs_modulus = true, poisson_ratio = true, density = true, damping = true;
  bool elastic() const { return youngs_modulus || poisson_ratio; }
};

// A run kept for reverse mode (Solver::record, Solver::run_adjoint): the state before every
// step and the end state, without their factor records, which are held once per distinct
// value in `factors` (a record changes only when the forward refactorises). The controls stay
// the caller's (run_adjoint is handed them again).
struct StoredRun {
  Scalar dt = 0;
  std::vector<State> states;          // (T + 1): x, v, time, step; factor left empty
  std::vector<FactorRecord> factors;  // the distinct records, in order of first use
  std::vector<Index> factor_of;       // (T + 1): each state's record in factors
  Index steps() const { return states.empty() ? 0 : static_cast<Index>(states.size()) - 1; }
};

class Solver {
 public:
  // The model must outlive the solver.
  Solver(const Model& model, const Config& config);

  const Model& model() const { return model_; }
  Config& config() { return config_; }
  const Config& config() const { return config_; }

  // One step of config().integrator. control: null or (n, d) forces [N] added to the external
  // force (fixed vertices ignore them). On failure (ConvergenceError, DivergenceError) the
  // caller restores the state (core/rollback.h); the solver stays usable.
  StepStats step(State& state, Scalar dt, Interrupt& interrupt, const Scalar* control = nullptr);

  // Equilibrium grad E(x) = M g with gravity ramped over load_steps Newton solves; sets v = 0.
  StepStats solve_static(State& state, Index load_steps, Interrupt& interrupt);

  // Vector-Jacobian product of step(before, dt, control) -> after. adjoint.x, adjoint.v hold
  // dL/d(after.x), dL/d(after.v) on entry and dL/d(before.x), dL/d(before.v) on return;
  // grad_control (n d, may be null) receives dL/du; params the parameter gradient of this step.
  // Throws NotPositiveDefinite when the exact Hessian of an implicit step's converged x is not
  // positive definite (no unique derivative of the minimiser there). wanted: the parameter
  // gradients to compute (the others are left empty / zero).
  void step_adjoint(const State& before, const State& after, Scalar dt, const Scalar* control,
                    State& adjoint, ParameterGradient& params, Scalar* grad_control,
                    Interrupt& interrupt, const ParameterMask& wanted = {});

  // `steps` calls of step(state, dt, controls + k n d), every state kept in run (whose buffers
  // are reused when it holds an earlier run). controls: null or (steps, n, d) forces [N]. When a
  // step throws, state is left at the last completed step (as step-by-step calls leave it).
  void record(State& state, Scalar dt, Index steps, const Scalar* controls, StoredRun& run,
              Interrupt& interrupt);

  // step_adjoint over a stored run, last step first, in one call: adjoint holds dL/d(end state)
  // on entry and dL/d(first state) on exit; params receives the steps' parameter gradients
  // summed in that order (each step's value added to the sum of the later ones: the sums a
  // caller adding step_adjoint's results step by step forms, bit for bit); controls: the run's
  // (null or T n d); grad_controls (T n d, or null) each step's dL/du.
  void run_adjoint(const StoredRun& run, const Scalar* controls, State& adjoint,
                   ParameterGradient& params, Scalar* grad_controls, Interrupt& interrupt,
                   const ParameterMask& wanted = {});

  Scalar elastic_energy(const Scalar* x) const;
  Scalar kinetic_energy(const Scalar* v) const;
  Scalar gravity_energy(const Scalar* x) const;  // - sum m g . x
  // f = -d(E + gravity potential)/dx, every vertex (fixed ones included).
  void forces(const Scalar* x, Scalar* f);
  // d^2 E / dx^2 (elastic part), values in pattern() order; returns the projected count.
  Index projected_hessian(const Scalar* x, bool project, Scalar* values);
  const ElementAssembly& pattern() const { return assembly_; }

  // Symplectic Euler's limit dt < 2 / omega_max, omega_max bounded by Gershgorin's theorem on
  // M^-1 K at the rest shape (computed once at construction; conservative).
  Scalar explicit_dt_limit() const { return explicit_dt_limit_; }

 private:
  template <int D> Scalar elastic_energy_d(const Scalar* x) const;
  template <int D> void elastic_gradient_d(const Scalar* x, Scalar* g);
  template <int D> Index elastic_hessian_d(const Scalar* x, bool project, Scalar* values);
  template <int D> void parameter_product_d(const Scalar* x, const Scalar* w, Scalar* g_mu,
                                            Scalar* g_lam) const;
  void elastic_gradient(const Scalar* x, Scalar* g);
  // out = K(x) w (exact elastic Hessian, every dof) without assembling it.
  void hessian_product(const Scalar* x, const Scalar* w, Scalar* out);
  // g_mu[e], g_lam[e] = w . d(grad E(x))/d(mu_e), d(grad E(x))/d(lam_e).
  void parameter_product(const Scalar* x, const Scalar* w, Scalar* g_mu, Scalar* g_lam) const;
  // params.youngs_modulus, .poisson_ratio = factor w . d(grad E(x))/d(E_e, nu_e), through
  // (mu_e, lam_e).
  void elastic_parameter_gradient(const Scalar* x, const Scalar* w, Scalar factor,
                                  ParameterGradient& params) const;
  // params.youngs_modulus, .poisson_ratio from g_mu, g_lam (per element) times factor.
  void lame_to_parameters(const std::vector<Scalar>& g_mu, const std::vector<Scalar>& g_lam,
                          Scalar factor, ParameterGradient& params) const;
  // The adjoints' one pass over the elements at x with the adjoint w: Kw = K(x) w (every dof);
  // with g_mu, g_lam non-null, parameter_product's; returns
  // sum_e vol_e P(F_e) : dF_e(w) = w . grad E(x) when work is true (else 0).
  template <int D> Scalar adjoint_elements_d(const Scalar* x, const Scalar* w, Scalar* Kw,
                                                Scalar* g_mu, Scalar* g_lam, bool work);

  StepStats step_implicit(State& state, Scalar dt, const Scalar* control, Interrupt& interrupt);
  StepStats step_symplectic(State& state, Scalar dt, const Scalar* control);
  // step_adjoint with the lagged factor's record the adjoint solve preconditions with given
  // (step_adjoint takes after's, or before's when after has none).
  void adjoint_step(const State& before, const State& after, const FactorRecord& factor,
                    Scalar dt, const Scalar* control, State& adjoint, ParameterGradient& params,
                    Scalar* grad_control, Interrupt& interrupt, const ParameterMask& wanted);
  void adjoint_implicit(const State& before, const State& after, const FactorRecord& factor,
                        Scalar dt, const Scalar* control, State& adjoint, ParameterGradient& params,
                        Scalar* grad_control, Interrupt& interrupt, const ParameterMask& wanted);
  void adjoint_symplectic(const State& before, const State& after, Scalar dt,
                          const Scalar* control, State& adjoint, ParameterGradient& params,
                          Scalar* grad_control, const ParameterMask& wanted);

  // Minimises  a/2 ||x - y||_M^2 + b/2 ||x - z||_M^2 + s (E(x) - load g.M x - u.x)  over the
  // free dofs starting from x, with a = inertia weight (0 for statics), u = control or none.
  StepStats minimise(State& state, Scalar* x, const Scalar* y, Scalar a, const Scalar* z,
                     Scalar b, Scalar s, Scalar load, const Scalar* control,
                     const Config& config, Interrupt& interrupt, const char* what);
  // Assembles (a + b) M + s K(x) (projected or not) with identity rows on fixed dofs.
  Index assemble_newton_matrix(const Scalar* x, Scalar a_plus_b, Scalar s, bool project);
  // Solves H dx = rhs with the matrix assembled at x (weight, scale, projected: its record) to
  // the relative residual tol (iterative solvers); false when CHOLMOD finds it indefinite.
  // reuse = false forces a factorisation. Keeps state's factor record up to date.
  bool linear_solve(State& state, const Config& config, const Scalar* rhs, Scalar* dx, Scalar tol,
                    bool reuse, const Scalar* x, Scalar weight, Scalar scale, bool projected,
                    StepStats& stats, Interrupt& interrupt);
  // Throws InvalidArgument naming a Config field out of range.
  void check_config() const;
  // Makes the solver's lagged factor the one state records (bitwise resume).
  void sync_factor(const State& state);
  void check_finite(const State& state, const std::vector<Scalar>& a, const char* quantity) const;

  const Model& model_;
  Config config_;
  ElementAssembly assembly_;
  // Scratch, allocated once.
  std::vector<Scalar> element_vectors_, element_matrices_, values_;
  std::vector<Scalar> grad_, dx_, trial_, rhs_;
  std::vector<Scalar> adjoint_w_, adjoint_kw_;  // the symplectic adjoint's w and K w
  SpdSolver spd_;
  // The adjoint solves' own factor and the forward record it is of (empty: H's own or none).
  SpdSolver adjoint_spd_;
  FactorRecord adjoint_factor_;
  // Which matrix spd_'s factor is, as State records it; force_refactor_: the next CHOLMOD
  // solve factorises (the State has no factor, or a pending refactorisation).
  FactorRecord factor_;
  bool force_refactor_ = false;
  Scalar explicit_dt_limit_ = 0;
  Scalar energy_scale_ = 0;  // sum_e V_e (2 mu_e + |lam_e|) d [J]: psi's term sizes at |F| ~ 1
  bool rigid_motion_free_ = true;  // the fixed vertices leave some rigid motion of the body free
  bool avx2_ = use_avx2();  // the neo-Hookean element passes' AVX2 version (core/simd.h)
  // The model's element constants packed for those passes (built on first use).
  const std::vector<lanes::Constants>& lane_constants() {
    if (lane_constants_.empty()) lane_constants_ = lanes::pack(model_);
    return lane_constants_;
  }
  std::vector<lanes::Constants> lane_constants_;
};

}  // namespace kinema::fem
