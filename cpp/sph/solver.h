// Smoothed particle hydrodynamics for liquids in kinema's four roles: Config (config.h), Model
// (model.h), State (state.h) and this Solver, which owns only scratch (cell grids, the step's
// exact neighbour lists and kernel gradients, per-particle work arrays); step() advances a State.
// Two pressure solvers:
// - WCSPH (Becker and Teschner 2007): Tait equation of state, symmetric pressure force,
//   symplectic Euler; explicit, so dt is bounded by the speed of sound.
// - DFSPH (Bender and Koschier 2015, 2017): a divergence-free solver and a constant-density
//   solver that correct velocities with per-particle stiffnesses kappa_i = alpha_i * error_i.
#pragma once

#include <memory>
#include <vector>

#include "core/interrupt.h"
#include "core/step_stats.h"
#include "core/types.h"
#include "sph/config.h"
#include "sph/model.h"
#include "sph/state.h"

namespace kinema::sph {

struct ParamsAdjoint;  // adjoint.h
struct AdjointScratch;  // adjoint.cpp

struct StepStats : StepStatsBase {
  int iterations = 0;             // DFSPH constant-density iterations
  int divergence_iterations = 0;  // DFSPH divergence-free iterations
  Scalar density_error = 0;       // mean compression max(rho/rho0 - 1, 0) (DFSPH: the density solve's error, of the
                                  // predicted densities; where a solve ends on a minimum iteration
                                  // begun within tol, the error before that iteration)
  Scalar divergence_error = 0;    // the divergence solve's error (DFSPH; likewise)
  // DFSPH: each solve ended within its tolerance (false: it stopped at max_iter with the error
  // above; WCSPH: always true). advance() counts the steps that did not.
  bool density_converged = true;
  bool divergence_converged = true;
  Scalar max_speed = 0;           // after the step [m/s]
  Index neighbor_count = 0;       // fluid-fluid neighbour entries (2 per pair)
  bool neighbor_rebuild = false;  // the neighbour lists were rebuilt from the cell grid
  // Where the step's wall time went [s]: the neighbour search (grid, Verlet lists, Morton
  // reordering), the kernel pass (exact pairs, densities, kernel gradients, DFSPH's alpha_i)
  // and the pressure solves (DFSPH: both; WCSPH: the pressure force).
  double search_seconds = 0;
  double kernel_seconds = 0;
  double solve_seconds = 0;
};

class Solver {
 public:
  // The model and config are copied; the config is checked (check(config)).
  Solver(const Model& model, const Config& config);
  ~Solver();
  Solver(Solver&&) noexcept;
  Solver& operator=(Solver&&) noexcept;

  // Advances state by dt. `forces` (n, d) [N] (or null) are external particle forces, added
  // where gravity is; row i is the force on particle i of the initial positions (state.ids),
  // so that it follows the particle through Morton reorderings. Throws InvalidArgument for a
  // bad dt or a state of another model, DivergenceError on non-finite values or runaway speeds
  // (the state is then partly advanced: callers that go on keep a copy, as the bindings do).
  StepStats step(State& state, Scalar dt, Interrupt& interrupt, const Scalar* forces = nullptr);

  // The vector-Jacobian product of one WCSPH step(before -> after) with the same dt (adjoint.cpp;
  // the forces enter additively, so their values are not needed). On entry adjoint.x and
  // adjoint.v ((n, d), the rows of `after`) hold dL/d(after); on return they hold dL/d(before)
  // (the rows of `before`). adjoint_params receives dL/d(viscosity) of this step and
  // adjoint_forces (n, d, rows by particle id as `forces`) dL/d(forces) when not null. The
  // neighbour set is the step's (the pairs within h at before's positions), not differentiated;
  // where the forward switched branch (Tait's clamp of negative pressures, the domain clamp)
  // this is the derivative of the branch taken. DFSPH is refused (InvalidArgument naming method).
  void step_adjoint(const State& before, const State& after, Scalar dt, State& adjoint,
                    ParamsAdjoint& adjoint_params, Scalar* adjoint_forces, Interrupt& interrupt);

  // The CFL time step cfl * spacing / (c + v_max) (WCSPH) or cfl * spacing / v_max (DFSPH),
  // also bounded by the viscous limit 0.05 spacing^2 / nu, sqrt(0.1 cfl spacing / |g|) and
  // kMaxDt.
  Scalar stable_dt(const State& state, Scalar cfl) const;
  // Recomputes the densities of the current positions into state.density (WCSPH: and the
  // pressures) and returns the mean over particles of max(rho/rho0 - 1, 0). Brings the
  // neighbour lists up to date as a step would.
  Scalar density_error(State& state);
  // Brings the neighbour lists up to date for the current positions exactly as step() does
  // (rebuilding or reordering if due) and returns the pairs i < j they hold (row indices, flat
  // [i0, j0, i1, j1, ...], in list order) and the (fluid, boundary sample) pairs.
  std::vector<Index> neighbor_pairs_in_use(State& state, std::vector<Index>& boundary_pairs);
  // Rebuilds state.lists as the step that built them did, from the positions x ((n, d)) and
  // skin they were built with (a checkpoint stores those rather than the lists).
  void restore_lists(State& state, const std::vector<Scalar>& x, Scalar skin);

  const Model& model() const;
  const Config& config() const;

  // Largest step stable_dt() returns without a CFL reason to go lower [s].
  static constexpr Scalar kMaxDt = 0.005;

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
  std::shared_ptr<AdjointScratch> adjoint_;  // step_adjoint's buffers and neighbour search
};

}  // namespace kinema::sph
