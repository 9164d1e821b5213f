// Lagrangian elastic bodies of linear triangles (2D, plane strain) or tetrahedra (3D), in the
// config / model / state / solver roles of STYLE.md.
// Implicit Euler is the minimisation of the incremental potential
//   g(x) = 1/2 ||x - (x_n + h v_n)||_M^2 + h c/2 ||x - x_n||_M^2 + h^2 (E(x) - f_ext . x),
// x_{n+1} = argmin g, v_{n+1} = (x_{n+1} - x_n)/h (Martin et al., "Example-based elastic
// materials", 2011; Gast et al., "Optimization integrator for large time steps", 2015), solved by
// projected Newton (element Hessians made positive semidefinite) with a backtracking (Armijo)
// line search, converged on the gradient norm relative to its value at the inertial guess.
// c is a mass-proportional (Rayleigh) damping rate [1/s].
#pragma once

#include <memory>
#include <vector>

#include "core/interrupt.h"
#include "fem/kernels.h"
#include "linalg/lagged_cholesky.h"
#include "mesh/element_assembly.h"

namespace kinema::fem {

struct BodyConfig {
  Material material = Material::NeoHookean;
  Scalar youngs_modulus = 0;   // E [Pa]
  Scalar poisson_ratio = 0;    // nu, in (-1, 0.5)
  Scalar density = 0;          // rho [kg/m^d] (2D: per unit thickness)
  Scalar damping = 0;          // c [1/s], mass-proportional
  std::vector<Scalar> gravity; // [m/s^2], empty or d entries; zero means no gravity pass
};

// What does not change during a step. Built by make_model, which validates everything.
struct BodyModel {
  int dim = 0;
  Index vertex_count = 0, element_count = 0;
  Material material = Material::NeoHookean;
  Scalar mu = 0, lam = 0, damping = 0;
  std::vector<Scalar> rest;        // (n, d) [m]
  std::vector<Index> elements;     // (m, d + 1), positively oriented
  std::vector<Scalar> Dm_inv;      // (m, d, d), column-major blocks
  std::vector<Scalar> volume;      // (m,) rest volume [m^d]
  std::vector<Scalar> mass;        // (n,) lumped vertex masses [kg]
  std::vector<unsigned char> fixed;  // (n,) 1 for a fixed vertex
  std::vector<Scalar> gravity;     // (d,) or empty
  Index fixed_count = 0;
  Scalar min_edge = 0;             // shortest rest edge [m], for the explicit step limit
  Scalar wave_speed = 0;           // sqrt((lam + 2 mu)/rho) [m/s]
};

// Throws InvalidArgument naming the first degenerate or inverted element by index.
BodyModel make_model(int dim, const Scalar* rest, Index vertex_count, const Index* elements,
                     Index element_count, const BodyConfig& config, const Index* fixed,
                     Index fixed_count);

struct BodyState {
  std::vector<Scalar> x, v;  // (n, d) [m], [m/s]
  Scalar time = 0;
  Index step = 0;
};

// Cholmod (default): PCG preconditioned by the most recent CHOLMOD factorisation, lagged across
// iterations and steps (linalg/lagged_cholesky.h), to the inexact-Newton forcing tolerance
// eta_k = max(min(cg_tol, |g_k|/|g_0|), 0.1 tol |g_0|/|g_k|): a residual relative to the
// gradient's own progress keeps Newton quadratic (eta_k = O(|g_k|)), and the second term stops
// solving more accurately than the stopping test needs. The matrix is refactorised when PCG
// needs more than 25 iterations or gives no descent direction. CholmodDirect: refactorise
// every Newton iteration (analysis reused). CholmodPcg: the lagged factor with the fixed
// tolerance cg_tol. CG: Jacobi-preconditioned CG on the projected matrix.
enum class LinearSolver { Cholmod, CholmodDirect, CholmodPcg, CG };

// Definiteness fix of the Newton matrix. Adaptive: the exact Hessian first, the per-element
// projected one only when CHOLMOD finds the exact matrix indefinite, which keeps Newton's
// quadratic convergence wherever the exact matrix is positive definite (clamping the near-zero
// rotational modes of every element would otherwise slow it to linear). CG always projects.
enum class Definiteness { Adaptive, Project, None };

struct NewtonOptions {
  Scalar tol = 1e-6;        // on ||grad g|| / ||grad g(x0)||
  Index max_iter = 50;
  LinearSolver linear_solver = LinearSolver::Cholmod;
  Scalar cg_tol = 1e-4;     // relative residual of each inexact Newton solve with CG
  Definiteness definiteness = Definiteness::Adaptive;
};

struct NewtonStats {
  Index iterations = 0;
  bool converged = false;
  std::vector<Scalar> gradient_norm;  // ||grad g|| at each iterate (absolute)
  std::vector<Scalar> step_length;    // accepted line-search step per iteration
  Index projected_elements = 0;       // elements whose dP/dF was clamped (last iteration)
  Index cg_iterations = 0;
  Index factorizations = 0;           // CHOLMOD numeric factorisations
  double seconds_assembly = 0, seconds_factor = 0, seconds_solve = 0, seconds_line_search = 0;
  double seconds = 0;
};

class Body {
 public:
  Body(BodyModel model, const BodyConfig& config);

  const BodyModel& model() const { return model_; }
  BodyState& state() { return state_; }
  const BodyState& state() const { return state_; }

  // Backward Euler by projected Newton. On failure (ConvergenceError, DivergenceError) the state
  // is left as it was before the call.
  NewtonStats step_implicit(Scalar dt, const NewtonOptions& options, Interrupt& interrupt);
  // v += dt M^-1 f(x), x += dt v (symplectic Euler); no Hessian is assembled.
  void step_symplectic(Scalar dt);
  // Equilibrium grad E(x) = f_ext with gravity ramped over load_steps Newton solves.
  NewtonStats solve_static(const NewtonOptions& options, Index load_steps, Interrupt& interrupt);

  Scalar elastic_energy(const Scalar* x) const;
  Scalar kinetic_energy() const;
  Scalar gravity_energy(const Scalar* x) const;  // - sum m g . x
  // f = -d(E + gravity potential)/dx, every vertex (fixed ones included).
  void forces(const Scalar* x, Scalar* f);
  // d^2 E / dx^2 (elastic part), values in pattern() order.
  Index projected_hessian(const Scalar* x, bool project, Scalar* values);
  const ElementAssembly& pattern() const { return assembly_; }

  // Symplectic Euler's limit dt < 2 / omega_max, omega_max bounded by Gershgorin's theorem on
  // M^-1 K at the rest shape (computed once at construction; conservative).
  Scalar explicit_dt_limit() const { return explicit_dt_limit_; }

 private:
  template <int D> Scalar elastic_energy_d(const Scalar* x) const;
  template <int D> void elastic_gradient_d(const Scalar* x, Scalar* g);
  template <int D> Index elastic_hessian_d(const Scalar* x, bool project, Scalar* values);
  void elastic_gradient(const Scalar* x, Scalar* g);
  // Minimises  a/2 ||x - y||_M^2 + b/2 ||x - z||_M^2 + s (E(x) - load g.M x)  over the free dofs
  // starting from x, with a = inertia weight (0 for statics).
  NewtonStats minimise(Scalar* x, const Scalar* y, Scalar a, const Scalar* z, Scalar b, Scalar s,
                       Scalar load, const NewtonOptions& options, Interrupt& interrupt,
                       const char* what);
  // Assembles (a + b) M + s K(x) (projected or not) with identity rows on fixed dofs.
  Index assemble_newton_matrix(const Scalar* x, Scalar a_plus_b, Scalar s, bool project);
  // Solves H dx = rhs with the assembled matrix to the relative residual tol (iterative
  // solvers); false when CHOLMOD finds it indefinite. reuse = false forces a factorisation.
  bool linear_solve(const NewtonOptions& options, const Scalar* rhs, Scalar* dx, Scalar tol,
                    bool reuse, NewtonStats& stats);
  void check_finite(const std::vector<Scalar>& a, const char* quantity) const;

  BodyModel model_;
  BodyState state_;
  ElementAssembly assembly_;
  // Scratch, allocated once.
  std::vector<Scalar> element_vectors_, element_matrices_, values_;
  std::vector<Scalar> grad_, dx_, trial_, rhs_;
  LaggedCholesky factor_;
  Scalar explicit_dt_limit_ = 0;
};

}  // namespace kinema::fem
