// Everything an MPM step reads and writes: the particles and the time. A copy of a State resumes
// bit for bit (the solver's block lists and grid are rebuilt from the positions every step).
// Rows keep the order in which particles were added (the solver sorts an index list into grid
// blocks, not the rows), so the slice add_particles returns stays valid. Buffers are
// reallocated only when particles are added.
#pragma once

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
  Scalar time = 0;               // [s]
  Index steps = 0;

  // Appends m particles at x0 (m, d) with velocity v0 (m, d), F = I, C = 0, Jp = 1 and the
  // moduli of their material.
  void append(const Scalar* x0, const Scalar* v0, Index m, const Scalar* mass0, const Scalar* volume0,
              Index material_code, Scalar youngs_modulus0, Scalar poisson_ratio0);
};

}  // namespace kinema::mpm
