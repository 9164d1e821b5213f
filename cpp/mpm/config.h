// Parameters of the material point method solver (MLS-MPM with APIC transfers, Hu et al. 2018;
// Jiang et al. 2015): a plain struct with defaults and units. What the particles are made of and
// where the walls are is the Model's (model.h); this is how the solver steps.
#pragma once

#include <array>

#include "core/types.h"

namespace kinema::mpm {

struct Config {
  std::array<Scalar, 3> gravity{0, 0, 0};  // [m/s^2], first d entries used; none by default
  // A step whose fastest particle crosses more than this many cells is a blow-up: the
  // DivergenceError names stable_dt. MPM's transfers assume particles move less than one cell
  // per step (the CFL rule of the course notes, CFL 0.3-1).
  Scalar max_cells_per_step = 2;
  // Largest step stable_dt returns when nothing moves and nothing is stiff [s].
  Scalar max_dt = 1e-2;
  // Steps of up to 65,536 particles may run on one thread when, measured every 256 steps, one
  // thread is clearly faster than the full team (contended cores; solver.cpp choose_team).
  // Results are the same bits either way.
  bool adapt_threads = true;
};

}  // namespace kinema::mpm
