// Vertex subsets given as index lists (fixed vertices, pinned handles), as per-vertex flags.
#pragma once

#include <algorithm>
#include <string>
#include <vector>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/types.h"

namespace kinema {

// flags[i] = 1 for each i in indices[0, count); an index outside [0, vertex_count) is an
// InvalidArgument naming `name`.
inline std::vector<unsigned char> vertex_flags(const Index* indices, Index count,
                                               Index vertex_count, const char* name) {
  std::vector<unsigned char> flags(vertex_count, 0);
  for (Index k = 0; k < count; ++k) {
    if (indices[k] < 0 || indices[k] >= vertex_count)
      throw InvalidArgument(std::string(name) + ": vertex index " + std::to_string(indices[k]) +
                            " outside [0, " + std::to_string(vertex_count) + ")");
    flags[indices[k]] = 1;
  }
  return flags;
}

// Kinetic energy sum_i m_i |v_i|^2 / 2 of lumped vertex masses; v is (count, dim) row-major.
inline Scalar lumped_kinetic_energy(const Scalar* mass, const Scalar* v, Index count, int dim) {
  return parallel_sum(count, [&](Index i) {
    Scalar v2 = 0;
    for (int r = 0; r < dim; ++r) v2 += v[i * dim + r] * v[i * dim + r];
    return mass[i] * v2 / 2;
  });
}

// Ends a time step of a vertex state {x, v, time, step}: the new positions and velocities are
// copied into the state's own buffers (numpy views alias them, so never swap), time and step
// count advance.
template <class VertexState>
void accept_step(VertexState& state, const std::vector<Scalar>& x, const std::vector<Scalar>& v,
                 Scalar dt) {
  std::copy(x.begin(), x.end(), state.x.begin());
  std::copy(v.begin(), v.end(), state.v.begin());
  state.time += dt;
  ++state.step;
}

}  // namespace kinema
