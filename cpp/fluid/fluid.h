// Incompressible Navier-Stokes on a MAC grid by operator splitting, 2D and 3D from one code path:
//   du/dt = -(u . grad) u + f + nu lap u - grad p,   div u = 0   (density 1, p kinematic),
// advanced per step as advect (kernels.h), add forces (gravity, buoyancy, vorticity
// confinement), implicit viscosity (backward Euler), and Chorin's projection, whose pressure
// Poisson problem is solved by kinema's MGPCG (grid/poisson_solver.h).
// Stam, "Stable fluids", SIGGRAPH 1999; Bridson, "Fluid Simulation for Computer Graphics",
// 2nd ed. (2015), Ch. 2-5 and 8; Fedkiw, Stam & Jensen, "Visual simulation of smoke",
// SIGGRAPH 2001 (buoyancy, vorticity confinement).
//
// Axes are internal: a 2D grid (nx, ny) is the 3D grid (1, nx, ny) with axis 0 inactive
// (grid/grid.h), so user axis c is internal axis c + 3 - dim. Velocity component a lives on
// face_layout(shape, a): u_a at the centre of the faces normal to axis a.
#pragma once

#include <array>
#include <memory>
#include <vector>

#include "core/interrupt.h"
#include "fluid/kernels.h"
#include "grid/poisson_solver.h"
#include "linalg/cg.h"
#include "linalg/solve_info.h"

namespace kinema::fluid {

// Parameters of a simulation (SI units, density 1).
struct FluidConfig {
  AdvectionScheme advection = AdvectionScheme::MacCormack;
  int rk_order = 2;                 // back-trace order, 1-3
  AdvectionKernel advection_kernel = AdvectionKernel::Auto;  // implementation (same results)
  PoissonMethod projection = PoissonMethod::MGPCG;
  Scalar tol = 1e-6;                // relative residual of the pressure solve
  Index max_iter = 0;               // 0: the solver's default
  Scalar viscosity = 0;             // kinematic viscosity nu [m^2/s]
  bool periodic = false;            // periodic on every axis (else closed walls)
  bool no_slip = false;             // closed walls: u = wall velocity (else free slip)
  // Open (outflow) sides, wall 2*axis + side (internal axes): pressure p = 0 on the side and
  // its normal velocity free, so fluid and smoke can leave (or enter) the domain there.
  std::array<bool, 6> open{};
  Vec3 gravity{0, 0, 0};            // [m/s^2], internal axes
  bool density = false, temperature = false;
  Scalar alpha = 0, beta = 0;       // buoyancy (-alpha rho + beta T) up [m/s^2 per unit]
  Vec3 up{0, 0, 0};                 // unit vector, internal axes
  Scalar vorticity_confinement = 0; // epsilon of Fedkiw et al. (dimensionless)
};

// What the user moves between steps (walls, obstacles) and the grid; the solver rebuilds its
// pressure hierarchy when `solid` changes.
struct FluidModel {
  GridShape shape;
  Scalar h = 1;                       // cell size [m]
  std::vector<std::uint8_t> solid;    // per cell, nonzero = solid (velocity 0 on its faces)
  std::array<Vec3, 6> wall_velocity{};  // wall 2*axis + side, tangential part only [m/s]
  std::array<bool, 6> wall_moving{};
  // Sources: values imposed before every step (inflows, emitters), applied in order.
  struct Source {
    std::vector<Index> cells;                // flat cell indices
    bool set_density = false, set_temperature = false;
    Scalar density = 0, temperature = 0;
    bool set_velocity = false;
    Vec3 velocity{0, 0, 0};                  // internal axes [m/s]: every free face of the cells
    std::array<std::vector<Index>, 3> faces; // the faces of the cells, per internal axis
  };
  std::vector<Source> sources;
};

// What evolves. Arrays are never reallocated, so views handed out stay valid.
struct FluidState {
  std::array<std::vector<Scalar>, 3> velocity;  // u_a on face_layout(a) [m/s]; empty if inactive
  std::vector<Scalar> pressure;                 // kinematic pressure p / rho [m^2/s^2], cells
  std::vector<Scalar> density, temperature;     // cells; empty unless enabled
  Scalar time = 0;                              // [s]
  Index steps = 0;
};

struct StepInfo {
  SolveInfo pressure;
  Scalar dt = 0, cfl = 0;           // the step and max |u| dt / h before it
  Index viscosity_iterations = 0;   // CG iterations over all components
  double advect = 0, forces = 0, viscosity = 0, projection = 0, total = 0;  // [s]
};

class FluidSolver {
 public:
  FluidSolver(const GridShape& shape, Scalar h, const FluidConfig& config);

  // One splitting step of size dt [s]. When it throws, the state is as it was before.
  StepInfo step(Scalar dt, Interrupt& interrupt);
  // Steps of dt = cfl h / u_max (u_max includes sqrt(5 h |g|), Bridson Sec. 3.2) until
  // `duration` has passed; returns the number of steps.
  Index advance(Scalar duration, Scalar cfl, Interrupt& interrupt, StepInfo* last = nullptr);

  // wall = 2*axis + side (internal axis); the velocity's normal component must be 0.
  void set_wall_velocity(int wall, const Vec3& velocity);
  // Adds a source over the cells where mask != 0 (one byte per cell); returns its index.
  Index add_source(const std::uint8_t* mask, bool set_density, Scalar density, bool set_temperature,
                   Scalar temperature, bool set_velocity, const Vec3& velocity);
  void clear_sources() { model_.sources.clear(); }

  void divergence(Scalar* out, Scalar scale = 1) const;  // scale * div u per cell [1/s]; 0 in solid cells
  Vec3 velocity_at(const Vec3& x) const;   // x in metres, internal axes
  Scalar kinetic_energy() const;           // 0.5 int |u|^2 dV [m^(d+2)/s^2]
  Scalar max_speed() const;                // max |u_a| over faces; +inf if any is non-finite

  FluidModel& model() { return model_; }
  const FluidModel& model() const { return model_; }
  FluidState& state() { return state_; }
  const FluidState& state() const { return state_; }
  const FluidConfig& config() const { return config_; }
  const FieldLayout& face(int axis) const { return faces_[axis]; }
  const FieldLayout& cells() const { return cells_; }

 private:
  StepInfo step_phases(Scalar dt, Interrupt& interrupt);  // step() without the rollback
  // The five phases of a step, in order.
  void advect(Scalar dt);
  void add_forces(Scalar dt);
  Index diffuse(Scalar dt, Interrupt& interrupt);
  SolveInfo project(Scalar dt, Interrupt& interrupt);
  void check(Scalar dt, Index step) const;  // throws DivergenceError naming field and step

  void refresh_solids();            // rebuilds face flags and the pressure solver on change
  void apply_sources();             // imposes the model's sources on the state
  void inflow_ambient(Scalar* const* fields, int count);  // scalars 0 where open sides take fluid in
  bool any_open() const { return config_.open != std::array<bool, 6>{}; }
  void enforce_boundary();          // fixed faces to their values, periodic copies in sync
  // u_a += dt * (face average of f) + du on the free faces
  void add_cell_force(int axis, const Scalar* f, Scalar dt, Scalar du);
  // Fedkiw et al. 2001, Eq. (9)-(11), plus the buoyancy when `buoyant`, into force_
  void confinement_force(bool buoyant);
  void apply_viscosity_operator(int axis, Scalar c, const Scalar* x, Scalar* y) const;
  MacVelocity mac_velocity() const;  // the state's velocity, with the walls
  void check_kernel() const;         // throws when a requested row kernel does not apply
  bool is_fixed(int axis, Index f) const { return fixed_[axis][f] != 0; }
  bool fluid_cell(Index c) const { return model_.solid.empty() || !model_.solid[c]; }
  // Neighbour of node idx along `axis` by `step` (+-1) in layout L, or -1 outside a closed domain.
  static Index neighbour(const FieldLayout& L, const std::array<Index, 3>& idx, int axis, int step);

  FluidModel model_;
  FluidConfig config_;
  FluidState state_;
  std::array<bool, 3> active_{};
  FieldLayout cells_;
  std::array<FieldLayout, 3> faces_;

  // Face flags: 1 where the velocity is prescribed (closed-wall normal faces, faces of solid
  // cells); 2 on a periodic domain's duplicate last face.
  std::array<std::vector<std::uint8_t>, 3> fixed_;
  // The faces of each flag, listed once per mask so enforce_boundary touches only them.
  std::array<std::vector<Index>, 3> pinned_faces_, duplicate_faces_;
  std::vector<std::uint8_t> solid_used_;  // the mask the flags and pressure solver were built for
  bool has_solid_ = false, built_ = false;

  std::unique_ptr<PoissonSolver> pressure_solver_;  // Neumann walls or periodic
  // Scratch, allocated once in the constructor (only what the configuration needs).
  std::array<std::vector<Scalar>, 3> velocity_new_;
  std::array<std::vector<Scalar>, 2> scalar_new_;  // density, temperature (those enabled)
  std::vector<Scalar> rhs_, residual_, rhs_face_, solution_face_;
  std::array<std::vector<Scalar>, 3> cell_velocity_, vorticity_, force_;
  std::vector<Scalar> vorticity_norm_;
  AdvectionScratch advection_scratch_;
  CgWorkspace viscosity_cg_;
  WallVelocities walls_;  // no-slip and moving walls as interpolation sees them
};

}  // namespace kinema::fluid
