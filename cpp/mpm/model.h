// What an MPM step does not change: the background grid (shape, spacing h, origin), the domain
// walls' boundary condition, the static colliders and the table of materials whose index is
// each particle's material code. Built and validated by the make_* factories; a Solver copies
// the Model it is built from.
//
// Grid convention (API.md): `shape` cells of spacing h span [origin, origin + shape h]; grid
// nodes sit at origin + i h for i = 0..shape, plus one ghost layer on each side (i = -1 and
// shape + 1) that the quadratic B-spline stencil of a particle on a wall reaches. The wall
// conditions hold on the nodes at and beyond the walls (i <= 0, i >= shape).
#pragma once

#include <array>
#include <string>
#include <vector>

#include "core/types.h"

namespace kinema::mpm {

// Velocity condition at a wall or collider with outward normal n (pointing into the material):
// Sticky: v = 0; Slip: v.n = 0; Separate: v.n = max(v.n, 0) (the material may leave the wall).
enum class Boundary { Sticky, Slip, Separate };

Boundary parse_boundary(const std::string& name, const char* argument);

enum class MaterialKind { Elastic, NeoHookean, Snow, Sand, Water };

MaterialKind parse_material(const std::string& name);
const char* material_name(MaterialKind kind);

struct Material {
  MaterialKind kind = MaterialKind::Elastic;
  Scalar density = 0;         // rest density rho0 [kg/m^d]
  Scalar youngs_modulus = 0;  // E [Pa] (water: the bulk modulus K)
  Scalar poisson_ratio = 0;   // nu [-]
  Scalar mu = 0, lambda = 0;  // Lame parameters [Pa]
  // Snow (Stomakhin et al. 2013, Sec. 5): singular values clamped to [1 - theta_c, 1 + theta_s];
  // the Lame parameters grow by exp(hardening (1 - Jp)).
  Scalar theta_c = 2.5e-2, theta_s = 7.5e-3, hardening = 10;
  // Sand (Klar et al. 2016, Sec. 7.3): alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi)) from the
  // friction angle phi; the cohesion c [Pa] moves the cone's apex to the tensile pressure
  // c / tan(phi) (Mohr-Coulomb), i.e. to the log-strain trace `apex_trace` (0 without cohesion).
  Scalar friction_angle = 0;  // [deg]
  Scalar cohesion = 0;        // [Pa]
  Scalar alpha = 0;
  Scalar apex_trace = 0;
  // Sand's friction law. Constant: the cone of friction_angle above (Klar et al.). MuI: the
  // mu(I) rheology of Jop, Forterre and Pouliquen 2006 (Nature 441, 727): the friction
  // coefficient mu = |tau| / p, with |tau| = sqrt(tau':tau' / 2), grows with the inertial number
  // I = gamma_dot d / sqrt(p / rho_s) as mu(I) = mu_s + (mu_2 - mu_s) / (I0 / I + 1); the return
  // mapping solves for the plastic shear rate that puts the stress on the mu(I) cone (as the
  // MPM of Dunatunga and Kamrin 2015, J. Fluid Mech. 779, 483, does implicitly). See
  // sand_project in kernels.h.
  enum class FrictionLaw { Constant, MuI } friction_law = FrictionLaw::Constant;
  Scalar mu_s = 0, mu_2 = 0;     // static and limiting friction coefficients [-]
  Scalar inertial_number0 = 0;   // I0 [-]
  Scalar grain_diameter = 0;     // d [m]
  Scalar grain_density = 0;      // rho_s [kg/m^d] (of the grains, not the bulk)
  // Water: Tait pressure p = K / gamma (J^-gamma - 1).
  Scalar gamma = 7;
  Scalar wave_speed = 0;  // speed of the fastest elastic wave at rest [m/s]
};

// Lame parameters from Young's modulus and Poisson's ratio (plane strain in 2D, as km.fem):
// mu = E / (2 (1 + nu)), lambda = E nu / ((1 + nu) (1 - 2 nu)). One expression for the material
// table and the per-particle moduli the solver reads, so both give the same bits.
inline void lame_parameters(Scalar youngs_modulus, Scalar poisson_ratio, Scalar& mu, Scalar& lambda) {
  mu = youngs_modulus / (2 * (1 + poisson_ratio));
  lambda = youngs_modulus * poisson_ratio / ((1 + poisson_ratio) * (1 - 2 * poisson_ratio));
}

// A validated material: `dim` fixes the Drucker-Prager constants of sand.
Material make_material(int dim, MaterialKind kind, Scalar density, Scalar youngs_modulus,
                       Scalar poisson_ratio, Scalar friction_angle, Scalar cohesion);

// Switches a sand material (made by make_material with friction_angle = atan(mu_s)) to the
// mu(I) friction law; validates the parameters (InvalidArgument naming the one at fault) and
// moves the cohesive apex to the tensile pressure c / mu_s.
void use_mu_i(Material& material, int dim, Scalar mu_s, Scalar mu_2, Scalar inertial_number0, Scalar grain_diameter,
              Scalar grain_density);

struct Collider {
  enum class Shape { Box, Sphere } shape = Shape::Box;
  std::array<Scalar, 3> lower{}, upper{};  // box corners [m]
  std::array<Scalar, 3> center{};          // sphere centre [m]
  Scalar radius = 0;                       // sphere radius [m]
  Boundary boundary = Boundary::Slip;
  Scalar friction = 0;  // Coulomb coefficient mu of slip and separate contact [-]
};

struct Model {
  int dim = 3;
  std::array<Index, 3> shape{1, 1, 1};  // cells per axis
  Scalar h = 0;                         // grid spacing [m]
  std::array<Scalar, 3> origin{};       // lower corner of the domain [m]
  Boundary boundary = Boundary::Slip;   // at the domain walls
  Scalar wall_friction = 0;             // Coulomb coefficient of the walls (slip, separate) [-]
  std::vector<Collider> colliders;
  std::vector<Material> materials;      // indexed by the particles' material codes

  Scalar upper(int axis) const { return origin[axis] + static_cast<Scalar>(shape[axis]) * h; }
};

Model make_model(int dim, const std::vector<Index>& shape, Scalar h, const std::vector<Scalar>& origin,
                 Boundary boundary, Scalar wall_friction = 0);

// Validates and appends a collider (its coordinates have dim entries).
void add_collider(Model& model, const Collider& collider);

}  // namespace kinema::mpm
