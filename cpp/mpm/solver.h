// The material point method solver: MLS-MPM (Hu et al. 2018) with APIC transfers (Jiang et al.
// 2015) and quadratic B-spline weights, in 2D and 3D. One step, in the order of Hu et al.'s
// Algorithm 1:
//   1. sort the particles into grid blocks (Morton order) and activate the blocks they touch
//      (a step that follows this solver's last step on the same, unchanged State, see
//      State::binning, keeps that binning and moves only the particles that left their block:
//      G2P lists them; the order is the same as a full sort's);
//   2. P2G: m_i = sum w m_p,  (m v)_i = sum w [m_p v_p + (m_p C_p - 4 dt V_p / h^2 tau_p)(x_i - x_p)];
//   3. grid update: v_i = (m v)_i / m_i + dt g, then the wall and collider conditions;
//   4. G2P: v_p = sum w v_i,  C_p = 4 / h^2 sum w v_i (x_i - x_p)^T,  x_p += dt v_p,
//      F_p <- (I + dt C_p) F_p and the material's plastic projection.
// step_adjoint runs these phases backwards (the vector-Jacobian product of one step, for
// km.diff): it rebuilds the step's grid from `before`, then G2P^T (a scatter, coloured as P2G),
// the grid update's transpose node by node, and P2G^T (a gather, per particle).
// The grid is sparse: storage and work exist only for the blocks of nodes that particles reach.
// Particles are visited block by block and, within a block, in user-row order (State::user),
// whatever order the rows are stored in, so no result depends on the stored order either.
// P2G needs no atomics and is deterministic for any thread count: each particle block scatters
// into its own tile of (B + 2)^d nodes, and the grid pass then gives every node the sum of the tiles over it in a fixed
// order (the block's own tile first), fused with the node's velocity update. A step is one
// parallel region whose phases (sort, P2G, grid, G2P) meet at barriers.
#pragma once

#include <memory>
#include <vector>

#include "core/interrupt.h"
#include "core/step_stats.h"
#include "core/types.h"
#include "mpm/config.h"
#include "mpm/model.h"
#include "mpm/state.h"

namespace kinema::mpm {

struct StepStats : StepStatsBase {
  Scalar max_speed = 0;         // largest particle speed after the step [m/s]
  Index particle_blocks = 0;    // grid blocks holding particles
  Index active_blocks = 0;      // blocks the transfers touch (with their +1 neighbours)
  Index rebinned = 0;           // particles binned anew: n after a full sort, else those that left their block
  Scalar sort_seconds = 0;      // binning into blocks and block activation
  Scalar p2g_seconds = 0;       // stress and particle-to-grid transfer
  Scalar grid_seconds = 0;      // grid velocity update and boundary conditions
  Scalar g2p_seconds = 0;       // grid-to-particle transfer, advection and plasticity
  int threads = 1;              // threads the step ran on (Config::adapt_threads)
};

// Gradients with respect to the per-particle parameters of one step.
struct ParamsAdjoint {
  std::vector<Scalar> youngs_modulus;  // (n,) dL/dE [1/Pa]
  std::vector<Scalar> poisson_ratio;   // (n,) dL/dnu
};

// Whether step_adjoint differentiates a material: the elastic ones and water, whose stresses
// and (water's) projection F <- J^(1/d) I are smooth functions of F (water's clamp of J at 1e-6:
// the branch taken). Snow's and sand's return mappings clamp singular values, whose SVD
// derivative has 1 / (sigma_i - sigma_j) terms that blow up at the repeated singular values
// every particle starts with (F = I).
bool differentiable_material(MaterialKind kind);

class Solver {
 public:
  Solver(const Model& model, const Config& config);
  ~Solver();
  Solver(const Solver&) = delete;
  Solver& operator=(const Solver&) = delete;

  // Advances state by dt. `forces` (n, d) [N] (or null) are external particle forces, added
  // where gravity is (the P2G momentum gains dt f_p). Throws InvalidArgument for particles
  // outside the domain or a bad dt, DivergenceError when a value turns non-finite or a particle
  // crosses more than config.max_cells_per_step cells in one step. A step that throws leaves
  // the state unchanged (it is transactional by itself; callers need no copy of the State).
  StepStats step(State& state, Scalar dt, Interrupt& interrupt, const Scalar* forces = nullptr);

  // Stores the rows of `state` in the block order of the step just taken (call it right after a
  // step that returned; the State must not have been changed since): the next steps' transfers
  // then read and write the particle arrays nearly sequentially, and each block's rows are one
  // contiguous range (threads taking different blocks share no cache line but at the ends). A
  // permutation of storage only: every later result is bitwise the same as without it, and
  // state.user / state.row record where each user row went. Parallel, O(n).
  void sort_rows(State& state);
  // Puts the rows back in user order (state.user and state.row become empty, state.binning 0).
  // O(n); nothing to do when they are already.
  void user_order(State& state);

  // The vector-Jacobian product of step(before -> after) with the same dt and forces.
  // On entry `adjoint`'s x, v, F, C (shapes as State's) hold dL/d(after); on return they hold
  // dL/d(before). `adjoint_params` receives dL/d(youngs_modulus, poisson_ratio) of this step
  // and `adjoint_forces` (n, d) dL/d(forces) when not null. Where the forward switched branch
  // (wall and collider conditions, friction sticking, the clamp of x to the domain) this is
  // the derivative of the branch taken. Elastic, neo-Hookean and water particles only: an
  // InvalidArgument names `material` otherwise (see differentiable_material).
  void step_adjoint(const State& before, const State& after, Scalar dt, const Scalar* forces, State& adjoint,
                    ParamsAdjoint& adjoint_params, Scalar* adjoint_forces, Interrupt& interrupt);

  // min(cfl h / (v_max + c_max), sqrt(cfl h / |g|), max_dt): the CFL rule with the fastest
  // elastic wave c_max = sqrt((lambda + 2 mu) / rho) (snow: with its hardening; water:
  // sqrt(K / rho)) of the materials present.
  Scalar stable_dt(const State& state, Scalar cfl) const;
  // h / (v_max + c_max): the step whose CFL number is 1 (infinity when nothing moves and nothing
  // is stiff), the limit a step is warned against (an estimate, not an exact stability bound).
  Scalar cfl_dt(const State& state) const;
  // v_max + c_max of stable_dt [m/s]. On the State this solver's last step left, unchanged
  // since (State::binning), it costs no pass over the particles: the step measured v_max and
  // snow's hardening in G2P, and the wave speeds of the moduli (which no step changes) are kept
  // from the first pass after a change. The same value, bit for bit, either way.
  Scalar signal_speed(const State& state) const;
  // Whether signal_speed(state) is read from the last step's measurement.
  bool speed_measured(const State& state) const;

  // Translational kinetic energy sum m |v|^2 / 2 [J].
  Scalar kinetic_energy(const State& state) const;
  // sum m v (d entries) [kg m/s].
  std::vector<Scalar> momentum(const State& state) const;
  // The angular momentum about the origin that APIC conserves (Jiang et al. 2015, Sec. 5.3):
  // sum m x x v plus the affine part m (h^2 / 4) eps : C^T of each particle; one entry in 2D
  // (the z component), three in 3D.
  std::vector<Scalar> angular_momentum(const State& state) const;

  const Model& model() const { return model_; }
  const Config& config() const { return config_; }

  class Impl;

 private:
  Model model_;
  Config config_;
  std::unique_ptr<Impl> impl_;
  std::vector<Scalar> spare_;  // scratch of user_order
};

}  // namespace kinema::mpm
