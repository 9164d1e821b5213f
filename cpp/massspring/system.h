// Mass-spring systems in 2D and 3D: Hooke springs with per-spring stiffness, rest length and
// damping, lumped vertex masses, fixed vertices and gravity (config / model / state / solver).
// Integrators, with f = f(x_n, v_n) and K = df/dx, C = df/dv (kernels.h):
//   explicit Euler:    x' = x + h v,  v' = v + h M^-1 f
//   symplectic Euler:  v' = v + h M^-1 f,  x' = x + h v'
//   implicit:          [M - h C - beta h^2 K] v' = M v + h f_spring+gravity(x_n),  x' = x + h v'
// the last the unified form of Baraff & Witkin 1998 (eq. 18 rewritten for v'): beta = 1 is
// backward Euler linearised once, beta = 1/2 trapezoid-like. The matrix is assembled into a
// pattern fixed at construction and factorised by CHOLMOD, whose analysis is reused every step.
#pragma once

#include <vector>

#include "core/interrupt.h"
#include "linalg/lagged_cholesky.h"
#include "mesh/element_assembly.h"

namespace kinema::massspring {

struct SystemModel {
  int dim = 0;
  Index vertex_count = 0, spring_count = 0;
  std::vector<Index> springs;        // (m, 2)
  std::vector<Scalar> stiffness;     // (m,) [N/m]
  std::vector<Scalar> rest_length;   // (m,) [m]
  std::vector<Scalar> damping;       // (m,) [N s/m], along the spring
  std::vector<Scalar> mass;          // (n,) [kg]
  std::vector<unsigned char> fixed;  // (n,)
  std::vector<Scalar> gravity;       // (d,) or empty (no gravity pass)
  bool any_damping = false;
};

// Validates and builds; scalars are broadcast by the caller (arrays of full length here).
SystemModel make_system(int dim, Index vertex_count, const Index* springs, Index spring_count,
                        const Scalar* stiffness, const Scalar* rest_length, const Scalar* damping,
                        const Scalar* mass, const Index* fixed, Index fixed_count,
                        const std::vector<Scalar>& gravity);

struct SystemState {
  std::vector<Scalar> x, v;  // (n, d) [m], [m/s]
  Scalar time = 0;
  Index step = 0;
};

enum class Integrator { Explicit, Symplectic, Implicit };
// Cholmod (default) and its older name CholmodPcg: PCG to cg_tol preconditioned by the CHOLMOD
// factorisation of an earlier step (lagged, linalg/lagged_cholesky.h), refreshed when PCG needs
// more than 25 iterations. CholmodDirect: factorise every step (analysis reused).
// CG: Jacobi-preconditioned CG.
enum class LinearSolver { Cholmod, CholmodDirect, CholmodPcg, CG };

struct StepStats {
  bool clamped = false;   // the exact Jacobian was not definite; the clamped one was used
  bool refactored = false;  // a CHOLMOD factorisation was computed in this step
  Index factorizations = 0;
  Index cg_iterations = 0;
  double seconds_assembly = 0, seconds_factor = 0, seconds_solve = 0, seconds = 0;
};

class System {
 public:
  System(SystemModel model, const Scalar* x0);

  const SystemModel& model() const { return model_; }
  SystemState& state() { return state_; }

  StepStats step(Scalar dt, Integrator integrator, Scalar beta, LinearSolver solver,
                 Scalar cg_tol, Interrupt& interrupt);

  Scalar kinetic_energy() const;
  Scalar spring_energy() const;
  Scalar gravity_energy() const;
  // f(x, v): springs, damping and gravity, every vertex.
  void forces(Scalar* f);
  // Gershgorin bound of the explicit limit dt < 2 / omega_max.
  Scalar explicit_dt_limit() const;

 private:
  template <int D> void forces_d(Scalar* f, bool with_damping);
  template <int D> void assemble_d(Scalar dt, Scalar beta, bool clamp);
  void check_finite(const std::vector<Scalar>& a, const char* quantity) const;

  SystemModel model_;
  SystemState state_;
  ElementAssembly assembly_;
  std::vector<Scalar> element_vectors_, element_matrices_, values_, f_, rhs_;
  LaggedCholesky factor_;
};

}  // namespace kinema::massspring
