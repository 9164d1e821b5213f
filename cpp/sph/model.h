// What a km.sph liquid does not change while it runs: dimension, spacing, support radius,
// particle mass, the static boundary samples with their volumes, the closed box and the speed
// of sound. Static solids are boundary samples with the volume correction of Akinci et al. 2012:
//   psi_b = rho0 / sum_k W_bk over the boundary samples k, rho_i = sum_j m W_ij + sum_b psi_b W_ib.
// The closed box's walls (the samples from wall_begin on) are lattice layers of known volume that
// carry a pressure of their own under WCSPH, as frozen fluid particles would (solver.cpp,
// "WCSPH's walls"): their density rho_b = wall_rho_b + sum_i m W_ib, with wall_rho_b =
// sum_k psi_k W_bk the boundary's own share.
// make_model builds and checks it (and the Config) once, where the data enters C++.
#pragma once

#include <array>
#include <vector>

#include "core/types.h"
#include "sph/config.h"
#include "sph/state.h"

namespace kinema::sph {

struct Model {
  int dim = 3;
  Scalar spacing = 0;                 // particle spacing [m]
  Scalar h = 0;                       // support radius 2 * spacing [m]
  Scalar mass = 0;                    // rho0 spacing^d [kg]
  Scalar speed_of_sound = 0;          // WCSPH's c, DFSPH's reference speed of its blow-up check [m/s]
  std::vector<Scalar> boundary_x;     // (M, d) boundary samples [m]
  std::vector<Scalar> boundary_psi;   // (M,) rho0 V_b (Akinci et al. 2012, eq. 4) [kg]
  // The samples from wall_begin on (the closed box's walls) carry pressure under WCSPH; for
  // each sample, wall_rho = sum_k psi_k W_bk [kg/m^d], the boundary's own share of rho_b.
  Index wall_begin = 0;
  std::vector<Scalar> wall_rho;
  bool has_domain = false;            // positions are clamped into [lower, upper]
  std::array<Scalar, 3> lower{}, upper{};

  Index boundary_count() const { return static_cast<Index>(boundary_psi.size()); }
};

// Checks every value of the config (names the option in the InvalidArgument).
void check(const Config& config);

// Builds the model of a liquid starting as `initial` (whose column height fixes the default
// speed of sound): boundary (M rows of dim coordinates) gets its Akinci volumes; with lower
// and upper (dim coordinates each), the walls of that closed box are added. Checks config too.
Model make_model(const Config& config, const State& initial, Scalar spacing, std::vector<Scalar> boundary,
                 const Scalar* lower, const Scalar* upper);

// Regular lattice filling [lower, upper] with first point at lower + spacing/2 (row-major).
std::vector<Scalar> block(int dim, const Scalar* lower, const Scalar* upper, Scalar spacing);
// Samples in `layers` layers just outside the walls of the box [lower, upper].
std::vector<Scalar> box_boundary(int dim, const Scalar* lower, const Scalar* upper, Scalar spacing,
                                 int layers);

}  // namespace kinema::sph
