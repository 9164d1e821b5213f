// Everything a MAC-grid fluid step evolves. The last pressure is the warm start of the next
// projection, so a copy of the State resumes bit for bit (the solver's other buffers are
// scratch). The Solver allocates the arrays (make_state) and never reallocates them, so views
// handed out stay valid.
#pragma once

#include <array>
#include <vector>

#include "core/types.h"

namespace kinema::grid {

struct State {
  std::array<std::vector<Scalar>, 3> velocity;  // u_a on face_layout(a) [m/s]; empty if inactive
  std::vector<Scalar> pressure;                 // kinematic pressure p / rho [m^2/s^2], cells
  std::vector<Scalar> density, temperature;     // cells; empty unless enabled
  Scalar time = 0;                              // [s]
  Index steps = 0;
};

}  // namespace kinema::grid
