// Incompressible Navier-Stokes on a MAC grid by operator splitting, 2D and 3D from one code path:
//   du/dt = -(u . grad) u + f + nu lap u - grad p,   div u = 0   (density 1, p kinematic),
// advanced per step as advect (kernels.h), add forces (gravity, buoyancy, vorticity
// confinement), implicit viscosity (backward Euler), and Chorin's projection, whose pressure
// Poisson problem is solved by kinema's MGPCG (poisson/poisson_solver.h).
// Stam, "Stable fluids", SIGGRAPH 1999; Bridson, "Fluid Simulation for Computer Graphics",
// 2nd ed. (2015), Ch. 2-5 and 8; Fedkiw, Stam & Jensen, "Visual simulation of smoke",
// SIGGRAPH 2001 (buoyancy, vorticity confinement).
//
// Axes are internal: a 2D grid (nx, ny) is the 3D grid (1, nx, ny) with axis 0 inactive
// (poisson/grid.h), so user axis c is internal axis c + 3 - dim. Velocity component a lives on
// face_layout(shape, a): u_a at the centre of the faces normal to axis a.
//
// The four roles: Config (config.h) says how to step, Model (model.h) what the box holds,
// State (state.h) what evolves, and the Solver owns the pressure hierarchy and every scratch
// buffer; step(state, dt) is the one way to advance.
#pragma once

#include <array>
#include <limits>
#include <memory>
#include <vector>

#include "core/advance.h"
#include "core/interrupt.h"
#include "core/step_stats.h"
#include "grid/adjoint.h"
#include "grid/config.h"
#include "grid/kernels.h"
#include "grid/model.h"
#include "grid/state.h"
#include "linalg/cg.h"
#include "linalg/solve_info.h"
#include "poisson/poisson_solver.h"

namespace kinema::grid {

struct StepStats : StepStatsBase {
  SolveInfo pressure;               // the projection's pressure solve
  Scalar cfl = 0;                   // max |u| dt / h before the step
  Index viscosity_iterations = 0;   // CG iterations over all components
  double advect_seconds = 0, forces_seconds = 0, viscosity_seconds = 0, projection_seconds = 0;
};

class Solver {
 public:
  // Checks the configuration against the model's grid (InvalidArgument naming the option).
  Solver(const Model& model, const Config& config);
  Solver(const Solver&) = delete;
  Solver& operator=(const Solver&) = delete;

  // A fluid at rest at time 0, its arrays sized for this model and configuration.
  State make_state() const;

  // One splitting step of size dt [s]. When it throws, the state is as it was before.
  // `control` (nullable): per-cell accelerations [m/s^2], (cells, dim) in user component order,
  // averaged to the free faces and added with the body forces (km.diff's controls).
  // kept (nullable): the step's advection scratch is left there (step_adjoint's `forward`).
  StepStats step(State& state, Scalar dt, Interrupt& interrupt, const Scalar* control = nullptr,
                 std::array<AdvectionScratch, 4>* kept = nullptr);

  // The vector-Jacobian product of step(before, dt, control) (adjoint.cpp): `adjoint` holds
  // dL/d(after) on entry (velocity, density, temperature; pressure ignored) and dL/d(before) on
  // return (pressure 0: it is only a warm start). grad_viscosity (nullable: not wanted) receives
  // dL/dnu of this step, grad_control (nullable, the control's shape) dL/dcontrol. Throws
  // InvalidArgument naming the option when the configuration is not differentiable
  // (check_differentiable). Without grad_viscosity only the advection's first passes are
  // recomputed (the rest of the step is linear in what it reads, or only dL/dnu reads it).
  // forward (nullable): the scratch step(before, dt, control, kept) left in `kept`; the
  // advection's first passes are then read from it instead of recomputed (the same bits).
  void step_adjoint(const State& before, Scalar dt, const Scalar* control, State& adjoint,
                    Scalar* grad_viscosity, Scalar* grad_control, Interrupt& interrupt,
                    const std::array<AdvectionScratch, 4>* forward = nullptr);
  void check_differentiable() const;
  // The projection alone (u -= dt grad p with the pressure solve) and its transpose, for tests.
  SolveInfo apply_projection(State& state, Scalar dt, Interrupt& interrupt) { return project(state, dt, interrupt); }
  // warm_step >= 0: the adjoint solve of the step from state.steps = warm_step starts from the
  // last one's solution when that was the step after it (a backward pass runs the steps in
  // reverse, and consecutive adjoint pressures differ little, as the forward pressures do).
  void projection_adjoint(std::array<std::vector<Scalar>, 3>& grad, Scalar dt, Interrupt& interrupt,
                          Index warm_step = -1);
  // Forgets the last adjoint pressure solution: the next step adjoint's solve starts from zero.
  // A backward pass calls it first, so its gradients depend on its own chain of adjoint steps
  // only, never on adjoint calls made before it (the same bits in any order of calls).
  void reset_adjoint_warm_start() { adjoint_pressure_step_ = -1; }
  // Sets the kinematic viscosity nu [m^2/s] (a differentiable parameter).
  void set_viscosity(Scalar viscosity);
  // Levels of the pressure solver's multigrid hierarchy (0 without one), for tests.
  int multigrid_levels() const { return pressure_solver_->multigrid() ? pressure_solver_->multigrid()->levels() : 0; }
  // The CFL step dt = cfl h / u_max, at most max_dt, where u_max = max |u| + sqrt(5 h |g|)
  // (Bridson 2015, Sec. 3.2: what gravity adds in one step) also counts the speeds of moving
  // walls and velocity sources, which accelerate a fluid at rest.
  Scalar stable_dt(const State& state, Scalar cfl,
                   Scalar max_dt = std::numeric_limits<Scalar>::infinity()) const;
  // Steps of stable_dt until `duration` has passed (core/advance.h); `last` receives the last
  // step's statistics when given.
  AdvanceResult advance(State& state, Scalar duration, Scalar cfl, Scalar max_dt, Interrupt& interrupt,
                        StepStats* last = nullptr);

  // wall = 2*axis + side (internal axis); the velocity's normal component must be 0.
  void set_wall_velocity(int wall, const Vec3& velocity);
  // Adds a source over the cells where mask != 0 (one byte per cell); returns its index.
  Index add_source(const std::uint8_t* mask, bool set_density, Scalar density, bool set_temperature,
                   Scalar temperature, bool set_velocity, const Vec3& velocity);
  void clear_sources() { model_.sources.clear(); }
  // The obstacle mask, one byte per cell (nonzero = solid); edits take effect at the next step.
  std::uint8_t* solid() { return model_.solid.data(); }

  void divergence(const State& state, Scalar* out, Scalar scale = 1) const;  // scale * div u per cell [1/s]; 0 in solid cells
  Vec3 velocity_at(const State& state, const Vec3& x) const;  // x in metres, internal axes
  Scalar kinetic_energy(const State& state) const;  // 0.5 int |u|^2 dV [m^(d+2)/s^2]
  Scalar max_speed(const State& state) const;       // max |u_a| over faces; +inf if any is non-finite

  const Model& model() const { return model_; }
  const Config& config() const { return config_; }
  const FieldLayout& face(int axis) const { return faces_[axis]; }
  const FieldLayout& cells() const { return cells_; }

 private:
  // step() without the rollback
  StepStats step_phases(State& state, Scalar dt, Interrupt& interrupt, const Scalar* control,
                        std::array<AdvectionScratch, 4>* kept);
  // The five phases of a step, in order.
  // kept (nullable): the advection scratch of the scalars (0) and of each velocity component
  // (1 + axis) is left there, for the adjoint (advect_adjoint's `forward`).
  void advect(State& state, Scalar dt, std::array<AdvectionScratch, 4>* kept = nullptr);
  void add_forces(State& state, Scalar dt, const Scalar* control);
  Index diffuse(State& state, Scalar dt, Interrupt& interrupt);
  SolveInfo project(State& state, Scalar dt, Interrupt& interrupt);
  void check(const State& state, Scalar dt, Index step) const;  // throws DivergenceError naming field and step

  void check_config() const;        // throws InvalidArgument naming the option
  void check_state(const State& state) const;  // throws unless the arrays fit make_state's
  void build_solids();              // face flags and the pressure solver for model_.solid
  void refresh_solids(State& state);  // build_solids when the mask changed, and the state with it
  void apply_sources(State& state) const;  // imposes the model's sources on the state
  // scalars 0 where open sides take fluid in
  void inflow_ambient(const State& state, Scalar* const* fields, int count) const;
  bool any_open() const { return config_.open != std::array<bool, 6>{}; }
  void enforce_boundary(State& state) const;  // fixed faces to their values, periodic copies in sync
  // u_a += dt * (face average of f[c * stride]) + du on the free faces
  void add_cell_force(State& state, int axis, const Scalar* f, Index stride, Scalar dt, Scalar du) const;
  // The transpose of add_cell_force's face average: out[c * stride] = sum over the free faces of
  // cell c of the face's weight times g[face].
  void cell_force_adjoint(int axis, const Scalar* g, Scalar* out, Index stride) const;
  // The adjoint of enforce_boundary: pinned faces get 0, a duplicate's gradient moves to face 0.
  void enforce_boundary_adjoint(std::array<std::vector<Scalar>, 3>& grad) const;
  // Fedkiw et al. 2001, Eq. (9)-(11), plus the buoyancy when `buoyant`, into force_
  void confinement_force(const State& state, bool buoyant);
  void apply_viscosity_operator(int axis, Scalar c, const Scalar* x, Scalar* y) const;
  // The velocity of `velocity` (a State's or a scratch of its layout), with the walls.
  MacVelocity mac_velocity(const std::array<std::vector<Scalar>, 3>& velocity) const;
  void check_kernel() const;         // throws when a requested row kernel does not apply
  bool is_fixed(int axis, Index f) const { return fixed_[axis][f] != 0; }
  bool fluid_cell(Index c) const { return model_.solid.empty() || !model_.solid[c]; }
  // Neighbour of node idx along `axis` by `step` (+-1) in layout L, or -1 outside a closed domain.
  static Index neighbour(const FieldLayout& L, const std::array<Index, 3>& idx, int axis, int step);

  Model model_;
  Config config_;
  std::array<bool, 3> active_{};
  FieldLayout cells_;
  std::array<FieldLayout, 3> faces_;

  // Face flags: 1 where the velocity is prescribed (closed-wall normal faces, faces of solid
  // cells); 2 on a periodic domain's duplicate last face.
  std::array<std::vector<std::uint8_t>, 3> fixed_;
  // The faces of each flag, listed once per mask so enforce_boundary touches only them.
  std::array<std::vector<Index>, 3> pinned_faces_, duplicate_faces_;
  std::vector<std::uint8_t> solid_used_;  // the mask the flags and pressure solver were built for
  bool has_solid_ = false;

  std::unique_ptr<PoissonSolver> pressure_solver_;  // Neumann walls or periodic
  // Scratch, allocated once in the constructor (only what the configuration needs).
  std::array<std::vector<Scalar>, 3> velocity_new_;
  std::array<std::vector<Scalar>, 2> scalar_new_;  // density, temperature (those enabled)
  std::vector<Scalar> rhs_, residual_, rhs_face_, solution_face_;
  std::array<std::vector<Scalar>, 3> cell_velocity_, vorticity_, force_;
  std::vector<Scalar> vorticity_norm_;
  AdvectionScratch advection_scratch_;
  CgWorkspace viscosity_cg_;
  std::array<AdvectionScratch, 4> adjoint_kept_;  // step_adjoint's advection scratch, kept from call to call
  // step_adjoint's and projection_adjoint's arrays, kept from call to call (AdjointScratch)
  State adjoint_s0_;
  std::array<std::vector<Scalar>, 3> adjoint_g0_;
  std::array<std::vector<Scalar>, 2> adjoint_scalar0_;
  std::vector<Scalar> adjoint_force_, adjoint_gp_, adjoint_w_, adjoint_r_;
  AdjointScratch adjoint_work_;
  std::vector<Scalar> adjoint_pressure_;  // the last adjoint pressure solution (a warm start)
  Index adjoint_pressure_step_ = -1;      // the step it belongs to, -1: none
  WallVelocities walls_;  // no-slip and moving walls as interpolation sees them
};

}  // namespace kinema::grid
