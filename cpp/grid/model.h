// What a MAC-grid fluid step reads but does not change: the grid, the obstacles, the moving
// walls and the sources. The user edits it between steps through the Solver (solid cells,
// set_wall_velocity, add_source), which checks each value as it enters and rebuilds its
// pressure hierarchy when the obstacles change.
#pragma once

#include <array>
#include <cstdint>
#include <vector>

#include "grid/kernels.h"
#include "poisson/grid.h"

namespace kinema::grid {

struct Model {
  GridShape shape;
  Scalar h = 1;                         // cell size [m]
  std::vector<std::uint8_t> solid;      // per cell, nonzero = solid (velocity 0 on its faces)
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

// An empty box of `shape` cells of size h [m]: no obstacles, walls at rest, no sources.
Model make_model(const GridShape& shape, Scalar h);

}  // namespace kinema::grid
