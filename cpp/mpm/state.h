// Everything an MPM step reads and writes: the particles and the time. A copy of a State resumes
// bit for bit (the solver's block lists and grid are rebuilt from the positions every step).
// Each particle has a user row: its index in the order particles were added (what the slice
// add_particles returns and the Python views show). The rows may be stored in another order:
// Solver::sort_rows stores them in grid-block order so that the transfers read memory
// sequentially, Solver::user_order puts them back. `user` and `row` record the permutation
// (both empty: stored in user order). No result depends on the stored order: the solver visits
// the particles of a block in user-row order and reports user rows (solver.h).
#pragma once

#include <cstdint>
#include <vector>

#include "core/types.h"

namespace kinema::mpm {

struct State {
  explicit State(int dim_ = 3) : dim(dim_) {}
  int dim;
  Index n = 0;
  std::vector<Scalar> x;         // (n, d) positions [m]
  std::vector<Scalar> v;         // (n, d) velocities [m/s]
  std::vector<Scalar> F;         // (n, d, d) elastic deformation gradient, row-major [-]
  std::vector<Scalar> C;         // (n, d, d) APIC affine velocity matrix [1/s]
  std::vector<Scalar> mass;      // (n,) [kg]
  std::vector<Scalar> volume;    // (n,) rest volume [m^d]
  std::vector<Index> material;   // (n,) index into Model::materials
  std::vector<Scalar> Jp;        // (n,) plastic volume ratio det(F_P) (snow, sand; 1 otherwise)
  // Per-particle elastic moduli, so that km.diff can differentiate with respect to each
  // particle's; they start as the material's and the step derives the Lame parameters from them
  // (model.h, lame_parameters). Water reads youngs_modulus as its bulk modulus K.
  std::vector<Scalar> youngs_modulus;  // (n,) E [Pa]
  std::vector<Scalar> poisson_ratio;   // (n,) nu [-]
  std::vector<Index> user;       // (n,) user row of each stored row, or empty (identity)
  std::vector<Index> row;        // (n,) stored row of each user row, or empty (identity)
  // The mark of the step that left this State (0: none). A Solver whose last step left this
  // mark on this State keeps that step's binning of the particles into grid blocks and re-bins
  // only those that left their block (solver.h); anything that changes x, material,
  // youngs_modulus, poisson_ratio or the rows outside Solver::step must set it to 0 (km.mpm's
  // bindings do whenever a numpy view is taken or alive). No result depends on it.
  std::uint64_t binning = 0;
  Scalar time = 0;               // [s]
  Index steps = 0;

  bool user_ordered() const { return user.empty(); }
  Index user_of(Index stored) const { return user.empty() ? stored : user[static_cast<size_t>(stored)]; }
  Index row_of(Index user_row) const { return row.empty() ? user_row : row[static_cast<size_t>(user_row)]; }

  // Appends m particles at x0 (m, d) with velocity v0 (m, d), F = I, C = 0, Jp = 1 and the
  // moduli of their material. The rows must be stored in user order (Solver::user_order).
  void append(const Scalar* x0, const Scalar* v0, Index m, const Scalar* mass0, const Scalar* volume0,
              Index material_code, Scalar youngs_modulus0, Scalar poisson_ratio0);
};

}  // namespace kinema::mpm
