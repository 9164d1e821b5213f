// Smoothed particle hydrodynamics for liquids, in the four roles of kinema's style guide:
// Config (parameters), Model (what a step does not change: spacing, mass, boundary samples and
// their volumes, domain), State (positions, velocities, densities, pressures, time) and Solver
// (neighbour grids, neighbour lists and scratch buffers; step() advances a State).
// Two pressure solvers:
// - WCSPH (Becker and Teschner 2007): Tait equation of state, symmetric pressure force,
//   symplectic Euler; explicit, so dt is bounded by the speed of sound.
// - DFSPH (Bender and Koschier 2015, 2017): a divergence-free solver and a constant-density
//   solver that correct velocities with per-particle stiffnesses kappa_i = alpha_i * error_i.
// Static solids are boundary samples with the volume correction of Akinci et al. 2012:
//   psi_b = rho0 / sum_k W_bk over the boundary samples k, rho_i = sum_j m W_ij + sum_b psi_b W_ib.
#pragma once

#include <array>
#include <memory>
#include <string>
#include <vector>

#include "core/interrupt.h"
#include "core/types.h"

namespace kinema::sph {

enum class Method { WCSPH, DFSPH };

Method parse_method(const std::string& name);

struct Config {
  Method method = Method::DFSPH;
  Scalar rho0 = 1000;                          // rest density [kg/m^d]
  Scalar viscosity = 0;                        // kinematic viscosity nu [m^2/s]; 0 skips the pass
  std::array<Scalar, 3> gravity{0, -9.81, 0};  // [m/s^2], first d entries used
  Scalar speed_of_sound = 0;                   // WCSPH c [m/s]; 0: 10 sqrt(2 |g| H), H the initial fluid height
  Scalar gamma = 7;                            // Tait exponent
  Scalar tol = 1e-3;                           // DFSPH: mean relative compression after the density solve
  Scalar divergence_tol = 1e-3;                // DFSPH: mean (d rho/dt) dt / rho0 after the divergence solve
  int max_iter = 100;                          // DFSPH: iterations per solve
  bool divergence_solve = true;                // DFSPH: run the divergence-free solver
  int reorder_every = 16;                      // least steps between Morton reorderings (0: never)
  Scalar neighbor_skin = 0.2;                  // Verlet skin of the neighbour lists, fraction of h
  Scalar warm_start = 0.5;                     // DFSPH: share of the last step's stiffnesses to start from
};

struct Model {
  int dim = 3;
  Scalar spacing = 0;                 // particle spacing [m]
  Scalar h = 0;                       // support radius 2 * spacing [m]
  Scalar mass = 0;                    // rho0 spacing^d [kg]
  std::vector<Scalar> boundary_x;     // (M, d) boundary samples [m]
  std::vector<Scalar> boundary_psi;   // (M,) rho0 V_b (Akinci et al. 2012, eq. 4) [kg]
  bool has_domain = false;            // positions are clamped into [lower, upper]
  std::array<Scalar, 3> lower{}, upper{};

  Index boundary_count() const { return static_cast<Index>(boundary_psi.size()); }
};

// Builds and validates a model: boundary (M rows of dim coordinates) gets its Akinci volumes.
Model make_model(int dim, Scalar spacing, Scalar rho0, std::vector<Scalar> boundary,
                 const Scalar* lower, const Scalar* upper);

// Everything that evolves; arrays are never reallocated, so numpy views of them stay valid.
// Reordering for locality permutes the rows in place: `ids` holds each row's original index.
struct State {
  State(int dim, Index n);
  int dim;
  Index n;
  std::vector<Scalar> x;         // (n, d) positions [m]
  std::vector<Scalar> v;         // (n, d) velocities [m/s]
  std::vector<Scalar> density;   // (n,) [kg/m^d], at the start of the last step
  std::vector<Scalar> pressure;  // (n,) [Pa], of the last step
  std::vector<Index> ids;        // (n,) original index of each row
  Scalar time = 0;               // [s]
  Index steps = 0;
};

struct StepStats {
  Scalar dt = 0;
  int iterations = 0;             // DFSPH constant-density iterations
  int divergence_iterations = 0;  // DFSPH divergence-free iterations
  Scalar density_error = 0;       // mean compression the density solve reached (DFSPH)
  Scalar divergence_error = 0;    // the divergence solve's error (DFSPH)
  Scalar max_speed = 0;           // after the step [m/s]
  Index neighbor_count = 0;       // fluid-fluid neighbour entries (2 per pair)
  bool neighbor_rebuild = false;  // the neighbour lists were rebuilt from the cell grid
  Scalar seconds = 0;
};

class Solver {
 public:
  virtual ~Solver() = default;
  // Builds the solver for a model and the initial state (which fixes the default c).
  static std::unique_ptr<Solver> create(const Model& model, const Config& config, const State& state);

  // Advances state by dt. Throws DivergenceError on non-finite values or runaway speeds.
  virtual StepStats step(State& state, Scalar dt, Interrupt& interrupt) = 0;
  // The CFL time step cfl * spacing / (c + v_max) (WCSPH) or cfl * spacing / v_max (DFSPH),
  // also bounded by the viscous limit 0.05 spacing^2 / nu, sqrt(0.1 cfl spacing / |g|) and
  // kMaxDt.
  virtual Scalar stable_dt(const State& state, Scalar cfl) const = 0;
  // Recomputes the densities of the current positions into state.density and returns the
  // mean over particles of max(rho/rho0 - 1, 0).
  virtual Scalar density_error(State& state) = 0;
  // Brings the neighbour lists up to date for the current positions exactly as step() does
  // (rebuilding or reordering if due) and returns the pairs i < j they hold (row indices, flat
  // [i0, j0, i1, j1, ...], in list order) and the (fluid, boundary sample) pairs.
  virtual std::vector<Index> neighbor_pairs_in_use(State& state, std::vector<Index>& boundary_pairs) = 0;
  // Forgets what is carried from step to step besides the state (the Verlet lists and the
  // positions they were built at, the reordering schedule, DFSPH's warm-start stiffnesses, the
  // last dt): the next step searches afresh and solves from cold. Runs that reset at the same
  // steps are functions of the state alone, so a checkpoint of the state resumes them exactly.
  virtual void reset_caches() = 0;

  const Model& model() const { return model_; }
  const Config& config() const { return config_; }
  Scalar speed_of_sound() const { return c_; }

  // Largest step advance() takes without a CFL reason to go lower [s].
  static constexpr Scalar kMaxDt = 0.005;

 protected:
  Solver(const Model& model, const Config& config) : model_(model), config_(config) {}
  Model model_;
  Config config_;
  Scalar c_ = 0;  // speed of sound (WCSPH) or reference speed (DFSPH) [m/s]
};

// Regular lattice filling [lower, upper] with first point at lower + spacing/2 (row-major).
std::vector<Scalar> block(int dim, const Scalar* lower, const Scalar* upper, Scalar spacing);
// Samples in `layers` layers just outside the walls of the box [lower, upper].
std::vector<Scalar> box_boundary(int dim, const Scalar* lower, const Scalar* upper, Scalar spacing,
                                 int layers);

}  // namespace kinema::sph
