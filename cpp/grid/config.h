// Parameters of the MAC-grid fluid (km.grid.Fluid): a plain struct with defaults and units.
// Vectors are on internal axes (a 2D grid is the 3D grid (1, nx, ny), poisson/grid.h), so user
// axis c is internal axis c + 3 - dim. Checked once, by the Solver's constructor.
#pragma once

#include <array>

#include "grid/kernels.h"
#include "poisson/poisson_solver.h"

namespace kinema::grid {

struct Config {
  AdvectionScheme advection = AdvectionScheme::MacCormack;
  int rk_order = 2;                 // back-trace order, 1-3
  AdvectionKernel advection_kernel = AdvectionKernel::Auto;  // implementation (same results)
  PoissonMethod projection = PoissonMethod::MGPCG;
  Scalar tol = 1e-6;                // relative residual of the pressure solve, in (0, 1)
  Index max_iter = 0;               // 0: the solver's default
  // 0: solve the pressure to tol. k > 0: the projection is exactly k multigrid V-cycles from a zero
  // pressure (tol, max_iter and projection unused): a fixed symmetric linear map, so its adjoint
  // is the same k cycles; the divergence it leaves is StepStats::pressure.residual.
  Index pressure_vcycles = 0;
  Scalar viscosity = 0;             // kinematic viscosity nu [m^2/s]
  bool periodic = false;            // periodic on every axis (else closed walls)
  bool no_slip = false;             // closed walls: u = wall velocity (else free slip)
  // Open (outflow) sides, wall 2*axis + side (internal axes): pressure p = 0 on the side and
  // its normal velocity free, so fluid and smoke can leave (or enter) the domain there.
  std::array<bool, 6> open{};
  Vec3 gravity{0, 0, 0};            // [m/s^2], internal axes
  bool density = false, temperature = false;  // carry these passive scalars
  Scalar alpha = 0, beta = 0;       // buoyancy (-alpha rho + beta T) up [m/s^2 per unit]
  Vec3 up{0, 0, 0};                 // unit vector, internal axes; 0: against gravity, else +y
  Scalar vorticity_confinement = 0; // epsilon of Fedkiw et al. (dimensionless), >= 0
};

}  // namespace kinema::grid
