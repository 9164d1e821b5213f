// Cell-centred grid geometry shared by the grid solvers. A 2D grid (nx, ny) is stored as the
// 3D grid (1, nx, ny) with axis 0 inactive, so one code path serves both dimensions and the
// flat index (i*n1 + j)*n2 + k matches numpy's C order for 2D and 3D arrays alike.
#pragma once

#include <array>
#include <string>
#include <vector>

#include "core/errors.h"
#include "core/types.h"

namespace kinema {

struct GridShape {
  int dim = 3;                 // 2 or 3
  std::array<Index, 3> n{1, 1, 1};  // internal sizes; n[0] == 1 when dim == 2

  GridShape() = default;
  // From a user shape (nx, ny) or (nx, ny, nz).
  explicit GridShape(const std::vector<Index>& shape) {
    if (shape.size() != 2 && shape.size() != 3)
      throw InvalidArgument("shape: expected 2 or 3 dimensions, got " + std::to_string(shape.size()));
    dim = static_cast<int>(shape.size());
    for (Index s : shape)
      if (s < 1) throw InvalidArgument("shape: every dimension must be >= 1");
    if (dim == 2) n = {1, shape[0], shape[1]};
    else n = {shape[0], shape[1], shape[2]};
  }

  Index size() const { return n[0] * n[1] * n[2]; }
  Index rows() const { return n[0] * n[1]; }  // lines along the fastest axis
  Index stride(int axis) const { return axis == 0 ? n[1] * n[2] : axis == 1 ? n[2] : 1; }
  bool active(int axis) const { return axis >= 3 - dim; }
  Index index(Index i, Index j, Index k) const { return (i * n[1] + j) * n[2] + k; }
  std::vector<Index> user_shape() const {
    return dim == 2 ? std::vector<Index>{n[1], n[2]} : std::vector<Index>{n[0], n[1], n[2]};
  }
};

// Periodic: every active axis wraps around (cell n-1 neighbours cell 0).
enum class Boundary { Dirichlet, Neumann, Periodic };

// Neighbour directions: bit 2*axis for the lower neighbour, 2*axis + 1 for the upper one.
constexpr int kDirections = 6;
constexpr std::uint8_t kFluidBit = 1u << 6;

}  // namespace kinema
