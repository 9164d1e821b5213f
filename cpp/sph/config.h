// The parameters of km.sph's liquids, with their defaults and units: the material (rest density,
// viscosity, gravity, WCSPH's equation of state) and the solver's knobs (pressure solver,
// tolerances, neighbour-list skin, reordering, warm start). Checked once, by make_model.
#pragma once

#include <array>
#include <string>

#include "core/types.h"

namespace kinema::sph {

// WCSPH: Becker and Teschner 2007; DFSPH: Bender and Koschier 2015, 2017.
enum class Method { WCSPH, DFSPH };

Method parse_method(const std::string& name);
const char* method_name(Method method);

struct Config {
  Method method = Method::DFSPH;
  Scalar rho0 = 1000;                        // rest density [kg/m^d]
  Scalar viscosity = 0;                      // kinematic viscosity nu [m^2/s]; 0 skips the pass
  std::array<Scalar, 3> gravity{0, 0, 0};    // [m/s^2], first d entries used
  Scalar speed_of_sound = 0;                 // WCSPH c [m/s]; 0: 10 sqrt(2 |g| H), H the initial fluid height
  Scalar gamma = 7;                          // Tait exponent
  Scalar tol = 1e-3;                         // DFSPH: mean relative compression after the density solve
  Scalar divergence_tol = 1e-3;              // DFSPH: mean (d rho/dt) dt / rho0 after the divergence solve
  int max_iter = 100;                        // DFSPH: iterations per solve
  bool divergence_solve = true;              // DFSPH: run the divergence-free solver
  int reorder_every = 16;                    // least steps between Morton reorderings (0: never)
  Scalar neighbor_skin = 0.2;                // Verlet skin of the neighbour lists, fraction of h
  Scalar warm_start = 0.5;                   // DFSPH: share of the last step's stiffnesses to start from
  // DFSPH: two-level density solve (a coarse correction in height, needs gravity): 1 on, 0 off,
  // -1 on where tol > kCoarseAutoTol (loose tolerances, where the one-level solve let a column at
  // rest bounce; at tighter ones it holds and the coarse steps cost more than they save).
  int coarse_correction = -1;
  // DFSPH with a domain: the walls' samples carry the Shepard average of their fluid
  // neighbours' stiffness (a force of constraint form: a column filling its tank keeps its
  // energy); false: each sample mirrors the stiffness of the particle it pushes (Akinci et al.
  // 2012's pressure mirroring, not conservative; solver.cpp, apply_kappa; issue 15).
  bool shepard_walls = true;
  static constexpr Scalar kCoarseAutoTol = 1e-3;
};

}  // namespace kinema::sph
