// Lagrangian elastic bodies of linear triangles (2D, plane strain) or tetrahedra (3D): the
// Config, Model and State roles of STYLE.md (the Solver is in fem/solver.h).
// Model: rest shape Dm^-1 and volumes, lumped masses m_i = sum_e rho V_e / (d + 1), per-element
// Lame parameters mu_e, lam_e from (E_e, nu_e) (fem/kernels.h, lame()), fixed-vertex mask.
#pragma once

#include <vector>

#include "core/types.h"
#include "fem/kernels.h"
#include "linalg/spd_solver.h"

namespace kinema::fem {

enum class Integrator { Implicit, Symplectic };

// Definiteness fix of the Newton matrix. Adaptive: the exact Hessian first, the per-element
// projected one only when CHOLMOD finds the exact matrix indefinite, which keeps Newton's
// quadratic convergence wherever the exact matrix is positive definite (clamping the near-zero
// rotational modes of every element would otherwise slow it to linear). CG always projects.
enum class Definiteness { Adaptive, Project, None };

// How a step is taken. linear_solver (linalg/spd_solver.h): with Cholmod (default) each Newton
// system is solved by PCG preconditioned with the lagged CHOLMOD factor to the inexact-Newton
// forcing tolerance eta_k = max(min(cg_tol, |g_k|/|g_0|), 0.1 tol |g_0|/|g_k|): a residual
// relative to the gradient's own progress keeps Newton quadratic (eta_k = O(|g_k|)), and the
// second term stops solving more accurately than the stopping test needs. CholmodPcg uses the
// fixed tolerance cg_tol; CholmodDirect factorises every iteration; CG (Jacobi) always projects.
struct Config {
  Integrator integrator = Integrator::Implicit;
  Scalar tol = 1e-6;         // Newton: ||grad g|| <= tol ||grad g(x0)||
  Index max_newton = 50;     // Newton iterations per step (per load step in solve_static)
  LinearSolver linear_solver = LinearSolver::Cholmod;
  Scalar cg_tol = 1e-4;      // relative residual of an inexact Newton solve (PCG / CG)
  Definiteness definiteness = Definiteness::Adaptive;
};

// The material inputs make_model validates. youngs_modulus and poisson_ratio hold one value
// (uniform) or one per element.
struct Parameters {
  Material material = Material::NeoHookean;
  std::vector<Scalar> youngs_modulus;  // E [Pa]
  std::vector<Scalar> poisson_ratio;   // nu, in (-1, 0.5)
  Scalar density = 0;                  // rho [kg/m^d] (2D: per unit thickness)
  Scalar damping = 0;                  // c [1/s], mass-proportional
  std::vector<Scalar> gravity;         // [m/s^2], empty or d entries; zero means no gravity pass
};

// What does not change during a step. Built by make_model, which validates everything.
struct Model {
  int dim = 0;
  Index vertex_count = 0, element_count = 0;
  Parameters parameters;           // as given (gravity emptied when all zero)
  std::vector<Scalar> mu, lam;     // (m,) Lame parameters [Pa]
  std::vector<Scalar> rest;        // (n, d) [m]
  std::vector<Index> elements;     // (m, d + 1), positively oriented
  std::vector<Scalar> Dm_inv;      // (m, d, d), column-major blocks
  std::vector<Scalar> volume;      // (m,) rest volume [m^d]
  std::vector<Scalar> mass;        // (n,) lumped vertex masses [kg]
  std::vector<unsigned char> fixed;  // (n,) 1 for a fixed vertex
  Index fixed_count = 0;

  Material material() const { return parameters.material; }
  Scalar damping() const { return parameters.damping; }
  const std::vector<Scalar>& gravity() const { return parameters.gravity; }
};

// Throws InvalidArgument naming the argument: a degenerate or inverted element by index, an
// out-of-range value, a wrongly sized parameter array.
Model make_model(int dim, const Scalar* rest, Index vertex_count, const Index* elements,
                 Index element_count, Parameters parameters, const Index* fixed, Index fixed_count);

// Which matrix the lagged CHOLMOD factor of the Cholmod solvers is: (weight M + scale K(x)),
// element Hessians projected or not, and whether the next solve must refactorise.
struct FactorRecord {
  std::vector<Scalar> x;  // (n, d) [m]; empty: no factor
  Scalar weight = 0, scale = 0;
  bool projected = false;
  bool refactor_pending = false;

  bool operator==(const FactorRecord& o) const {
    return x == o.x && weight == o.weight && scale == o.scale && projected == o.projected &&
           refactor_pending == o.refactor_pending;
  }
};

// Everything that evolves. Besides positions and velocities, the lagged factor of the Cholmod
// solver is part of what a step reads from the past (it preconditions the next step's PCG, so it
// decides the rounding of the answer); the State records it and the solver rebuilds the same
// factor from a copied State, so that a resumed run is bitwise the run that was not stopped.
struct State {
  std::vector<Scalar> x, v;  // (n, d) [m], [m/s]
  Scalar time = 0;           // [s]
  Index step = 0;
  FactorRecord factor;
};

// The rest state: x = rest, v = 0, time 0, no factor.
State initial_state(const Model& model);

}  // namespace kinema::fem
