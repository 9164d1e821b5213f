// Implicit Euler with Incremental Potential Contact (Li et al., "Incremental Potential
// Contact", ACM TOG 39(4), 2020, algorithm 1): each step minimises
//   Phi(x) = 1/2 |x - xhat|_M^2 + h^2 (Psi(x) + D(x)) + kappa sum_k b(d_k(x)),   xhat = x_n + h v_n + h^2 g
// (Psi: tetrahedral and spring elasticity; b: the log barrier on every pair closer than dhat;
// D: friction lagged at x_n) by projected Newton (per-element and per-contact PSD projection)
// with a backtracking line search clamped by continuous collision detection, so every
// accepted iterate, and the straight path to it, is free of intersections.
#pragma once

#include <Eigen/SparseCore>
#include <cstdint>
#include <memory>
#include <vector>

#include "contact/block_cholesky.h"
#include "contact/collision.h"
#include "contact/model.h"
#include "contact/solver_system.h"
#include "core/interrupt.h"
#include "core/step_stats.h"
#include "linalg/spd_solver.h"

namespace kinema::contact {

struct StepStats : StepStatsBase {
  Index newton_iterations = 0;
  Index line_search_halvings = 0;  // total over the Newton iterations
  Index contact_count = 0;         // active pairs (closer than dhat) at the end of the step
  Scalar min_distance = 0;         // smallest distance among them [m]; inf when there is none
  Index sticking_count = 0;        // friction contacts slipping slower than friction_velocity
  Index sliding_count = 0;         // ... and faster
  Scalar min_step_fraction = 1;    // smallest CCD clamp of a Newton step (1: never clamped)
  double ccd_seconds = 0;          // wall time in continuous collision detection [s]
  Scalar ccd_share = 0;            // ccd_seconds / seconds
  Scalar barrier_stiffness = 0;    // kappa of the step [kg/m^2] (Phi units)
  double assemble_seconds = 0, solve_seconds = 0, line_search_seconds = 0;  // wall time per phase [s]
  // Parts of those: the numeric factorisations (in solve_seconds) and the broad phases (in
  // ccd_seconds, but for one before the Newton loop, when the state moved since the last step
  // ended, and a driven collider's last move) [s]; how many broad phases ran (the kept
  // candidates cover the other sweeps).
  double factor_seconds = 0, broad_phase_seconds = 0;
  Index broad_phases = 0;
  // Symbolic analyses of the Newton matrix in this step: its pattern changed (a contact block
  // not reserved yet, or reserved blocks dropped at the step's start; every iteration when
  // Config::reuse_pattern is off). The other factorisations reuse the analysis.
  Index pattern_changes = 0;
  Index unknowns = 0;  // size of the Newton system (3 per degree of freedom)
  // Per Newton iteration: max |dx| / (dt * bbox diagonal) (the quantity tol bounds) and the
  // step length accepted by the line search.
  std::vector<Scalar> newton_history, step_history;
};

// One friction contact lagged at x_n: relative motion u = P^T sum_a w_a (x_a - x_n,a).
struct FrictionContact {
  std::array<Index, 4> v;
  int count = 0;
  Scalar w[4] = {0, 0, 0, 0};
  Eigen::Matrix<Scalar, 3, 2> P;
  Scalar normal_force = 0;  // lambda [N]
  Scalar mu = 0;            // its Coulomb coefficient
};

class Solver {
 public:
  Solver(const Model& model, const Config& config);

  // Advances by dt; throws InvalidArgument when the state intersects (naming the elements),
  // ConvergenceError when Newton does not reach tol within max_newton iterations.
  StepStats step(State& state, Scalar dt, Interrupt& interrupt);

  // Elastic energy Psi(x) [J] (tests and diagnostics).
  Scalar elastic_energy(const Scalar* x) const;
  // Barrier energy sum_k b(d_k(x)) [m^4] and its gradient (3n) and Hessian (made PSD or not).
  Scalar barrier_energy(const Scalar* x) const;
  void barrier_gradient(const Scalar* x, Scalar* g) const;
  // The Hessian as CSR arrays (3n rows; row pointers, column indices sorted in each row,
  // values), assembled directly from the contact blocks; I is int32_t or int64_t (the caller
  // checks that the entries fit).
  template <class I>
  void barrier_hessian(const Scalar* x, Projection projection, std::vector<I>& ptr, std::vector<I>& col,
                       std::vector<Scalar>& val) const;
  // The active pairs at x and the largest collision-free fraction of the move x -> x + dx,
  // on the solver's broad phase (its trees refit, not rebuilt).
  std::vector<Constraint> constraints(const Scalar* x) const;
  Scalar max_safe_step(const Scalar* x, const Scalar* dx) const;

  // Throws InvalidArgument when x intersects (edges through triangles, vertices behind planes).
  void check_intersection_free(const Scalar* x, const char* name) const;

  const Model& model() const { return model_; }
  const Config& config() const { return config_; }

 private:
  // Phi(x); `constraints` are x's active pairs when `known`, else they are found and returned.
  Scalar potential(const std::vector<Scalar>& x, Scalar h, Scalar kappa, std::vector<Constraint>& constraints,
                   bool known) const;
  void assemble(const std::vector<Scalar>& x, Scalar h, Scalar kappa, const std::vector<Constraint>& constraints,
                std::vector<Scalar>& g, NewtonSystem& system) const;
  void lag_friction(const std::vector<Scalar>& x, const std::vector<Constraint>& constraints, Scalar kappa, Scalar h);
  Scalar initial_kappa(Scalar h) const;
  void refresh_slots(const NewtonSystem& system);
  // Keeps candidates_ covering the sweep x -> x + p (p may be null): true when the broad phase
  // ran, false when the kept candidates already cover it (force: run it). A broad phase that
  // runs covers the longer sweep x -> x + reach p.
  bool keep_candidates(const Scalar* x, const Scalar* p, Scalar reach, bool force, StepStats& stats);

  const Model& model_;
  Config config_;
  Scalar dhat2_;
  // Per-step scratch: the inertia target, the state at the step's start and lagged friction.
  std::vector<Scalar> xhat_, xn_, sweep_;
  std::vector<Scalar> target_, driven_lambda_;  // driven vertices' targets and multipliers (3n)
  Scalar driven_stiffness_ = 0;                 // k of the augmented Lagrangian [kg]
  std::vector<Vec3> spring_direction_;          // unit spring directions at x_n
  std::vector<FrictionContact> friction_;
  // The Newton matrix on its kept pattern and the factorisation of that pattern (analysed
  // once per pattern version).
  std::unique_ptr<NewtonSystem> system_;
  // Where the elastic blocks live in system_'s values (per vertex its diagonal block, then 16
  // per tet, 4 per spring), refreshed when its layout changes.
  std::vector<NewtonSystem::Slot> elastic_slots_;
  const NewtonSystem* slots_system_ = nullptr;
  std::int64_t slots_layout_ = -1;
  std::unique_ptr<SpdSolver> linear_;
  std::int64_t linear_version_ = -1;
  // Config::simplicial: the 3x3-block Cholesky of the system in its own dof order (AMD of the
  // elastic pattern, fixed), analysed once per pattern version.
  BlockCholesky block_llt_;
  // Broad phase kept between queries (its trees are refit), and the candidate pairs of the
  // current Newton iteration: boxes swept over x -> x + p grown by dhat, so every trial of the
  // line search (x + alpha p, alpha <= 1) finds its active pairs among them.
  mutable BroadPhase broad_phase_;
  Candidates candidates_;
  // The positions the last step ended at and their active pairs (the next step's pairs at x_n
  // when the state was not moved in between).
  std::vector<Scalar> end_x_;
  std::vector<Constraint> end_constraints_;
  // The region the candidates cover: per coordinate, the sweep they were found for grown by a
  // margin; a sweep inside it reuses them (no broad phase).
  std::vector<Scalar> cover_lo_, cover_hi_, reach_;
  // Per-contact barrier derivatives, kept so that their storage (a
  // few hundred kB, beyond malloc's mmap threshold) is not returned to the system and faulted
  // in again on every evaluation.
  mutable std::vector<Vec<12>> barrier_gradients_;
  mutable std::vector<Mat<12>> barrier_hessians_;
  // The Hessian's CSR assembly scratch: its 3x3 blocks bucketed by row vertex.
  struct HessianEntry {
    Index col, contact;
    int a, b;
  };
  mutable std::vector<HessianEntry> hessian_entries_;
  mutable std::vector<Index> hessian_row_start_, hessian_row_next_, hessian_row_blocks_;
};

}  // namespace kinema::contact
