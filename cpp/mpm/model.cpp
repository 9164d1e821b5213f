// Factories of the MPM model: every argument is checked here, once, where it enters C++.
#include "mpm/model.h"

#include <cmath>

#include "core/errors.h"
#include "mpm/state.h"

namespace kinema::mpm {

namespace {

constexpr Scalar kPi = 3.14159265358979323846;

bool finite_positive(Scalar v) { return std::isfinite(v) && v > 0; }

std::string boundary_names() { return "'sticky', 'slip' or 'separate'"; }

}  // namespace

Boundary parse_boundary(const std::string& name, const char* argument) {
  if (name == "sticky") return Boundary::Sticky;
  if (name == "slip") return Boundary::Slip;
  if (name == "separate") return Boundary::Separate;
  throw InvalidArgument(std::string(argument) + ": expected " + boundary_names() + ", got '" + name + "'");
}

MaterialKind parse_material(const std::string& name) {
  if (name == "elastic") return MaterialKind::Elastic;
  if (name == "neohookean") return MaterialKind::NeoHookean;
  if (name == "snow") return MaterialKind::Snow;
  if (name == "sand") return MaterialKind::Sand;
  if (name == "water") return MaterialKind::Water;
  throw InvalidArgument("material: expected 'elastic', 'neohookean', 'snow', 'sand' or 'water', got '" +
                        name + "'");
}

const char* material_name(MaterialKind kind) {
  switch (kind) {
    case MaterialKind::Elastic: return "elastic";
    case MaterialKind::NeoHookean: return "neohookean";
    case MaterialKind::Snow: return "snow";
    case MaterialKind::Sand: return "sand";
    case MaterialKind::Water: return "water";
  }
  return "?";
}

Material make_material(int dim, MaterialKind kind, Scalar density, Scalar youngs_modulus,
                       Scalar poisson_ratio, Scalar friction_angle, Scalar cohesion) {
  if (!finite_positive(density))
    throw InvalidArgument("density: expected a finite number > 0 [kg/m^d], got " + format_real(density));
  if (!finite_positive(youngs_modulus))
    throw InvalidArgument("youngs_modulus: expected a finite number > 0 [Pa], got " + format_real(youngs_modulus));
  Material m;
  m.kind = kind;
  m.density = density;
  m.youngs_modulus = youngs_modulus;
  if (kind == MaterialKind::Water) {
    m.wave_speed = std::sqrt(youngs_modulus / density);
    return m;
  }
  // Plane strain in 2D, as km.fem: the same Lame parameters in both dimensions.
  if (!(std::isfinite(poisson_ratio) && poisson_ratio > -1 && poisson_ratio < 0.5))
    throw InvalidArgument("poisson_ratio: expected a number in (-1, 0.5), got " + format_real(poisson_ratio));
  m.poisson_ratio = poisson_ratio;
  lame_parameters(youngs_modulus, poisson_ratio, m.mu, m.lambda);
  m.wave_speed = std::sqrt((m.lambda + 2 * m.mu) / density);
  if (kind == MaterialKind::Sand) {
    if (!(std::isfinite(friction_angle) && friction_angle > 0 && friction_angle < 90))
      throw InvalidArgument("friction_angle: sand needs an angle in (0, 90) degrees, got " +
                            format_real(friction_angle));
    if (!(std::isfinite(cohesion) && cohesion >= 0))
      throw InvalidArgument("cohesion: expected a number >= 0 [Pa], got " + format_real(cohesion));
    const Scalar s = std::sin(friction_angle * kPi / 180);
    m.friction_angle = friction_angle;
    m.cohesion = cohesion;
    m.alpha = std::sqrt(2.0 / 3.0) * 2 * s / (3 - s);
    // Apex at the tensile mean stress c / tan(phi): tr(eps) = d p / (d lambda + 2 mu).
    const Scalar p_apex = cohesion / std::tan(friction_angle * kPi / 180);
    m.apex_trace = dim * p_apex / (dim * m.lambda + 2 * m.mu);
  }
  return m;
}

void use_mu_i(Material& m, int dim, Scalar mu_s, Scalar mu_2, Scalar inertial_number0, Scalar grain_diameter,
              Scalar grain_density) {
  if (m.kind != MaterialKind::Sand) throw InvalidArgument("friction_law: 'mu_i' is a law of sand only");
  if (!finite_positive(mu_s)) throw InvalidArgument("mu_s: expected a finite number > 0, got " + format_real(mu_s));
  if (!(std::isfinite(mu_2) && mu_2 >= mu_s))
    throw InvalidArgument("mu_2: expected a finite number >= mu_s = " + format_real(mu_s) + ", got " + format_real(mu_2));
  if (!finite_positive(inertial_number0))
    throw InvalidArgument("I0: expected a finite number > 0, got " + format_real(inertial_number0));
  if (!finite_positive(grain_diameter))
    throw InvalidArgument("grain_diameter: expected a finite number > 0 [m], got " + format_real(grain_diameter));
  if (!finite_positive(grain_density))
    throw InvalidArgument("grain_density: expected a finite number > 0 [kg/m^d], got " + format_real(grain_density));
  m.friction_law = Material::FrictionLaw::MuI;
  m.mu_s = mu_s;
  m.mu_2 = mu_2;
  m.inertial_number0 = inertial_number0;
  m.grain_diameter = grain_diameter;
  m.grain_density = grain_density;
  m.apex_trace = dim * (m.cohesion / mu_s) / (dim * m.lambda + 2 * m.mu);
}

Model make_model(int dim, const std::vector<Index>& shape, Scalar h, const std::vector<Scalar>& origin,
                 Boundary boundary, Scalar wall_friction) {
  if (dim != 2 && dim != 3) throw InvalidArgument("shape: expected 2 or 3 entries");
  if (static_cast<int>(shape.size()) != dim)
    throw InvalidArgument("shape: expected " + std::to_string(dim) + " entries, got " + std::to_string(shape.size()));
  if (static_cast<int>(origin.size()) != dim)
    throw InvalidArgument("origin: expected " + std::to_string(dim) + " coordinates, got " +
                          std::to_string(origin.size()));
  if (!finite_positive(h)) throw InvalidArgument("h: expected a finite spacing > 0 [m], got " + format_real(h));
  Model m;
  m.dim = dim;
  m.h = h;
  m.boundary = boundary;
  if (!(std::isfinite(wall_friction) && wall_friction >= 0))
    throw InvalidArgument("friction: expected a number >= 0, got " + format_real(wall_friction));
  m.wall_friction = wall_friction;
  Scalar nodes = 1;
  for (int a = 0; a < dim; ++a) {
    if (shape[a] < 2 || shape[a] > (Index{1} << 20))
      throw InvalidArgument("shape: expected between 2 and 2^20 cells per axis, got " + std::to_string(shape[a]));
    if (!std::isfinite(origin[a])) throw InvalidArgument("origin: expected finite coordinates");
    m.shape[a] = shape[a];
    m.origin[a] = origin[a];
    nodes *= static_cast<Scalar>(shape[a] + 3);
  }
  // The block table is dense (one int per 4^3 or 8^2 nodes): keep it below 2^31 entries.
  if (nodes > 1e12) throw InvalidArgument("shape: grid too large (more than 1e12 nodes)");
  return m;
}

void add_collider(Model& model, const Collider& c) {
  if (!(std::isfinite(c.friction) && c.friction >= 0))
    throw InvalidArgument("friction: expected a number >= 0, got " + format_real(c.friction));
  for (int a = 0; a < model.dim; ++a) {
    if (c.shape == Collider::Shape::Box) {
      if (!(std::isfinite(c.lower[a]) && std::isfinite(c.upper[a]) && c.upper[a] > c.lower[a]))
        throw InvalidArgument("region: a box needs finite 'lower' < 'upper' on every axis");
    } else if (!std::isfinite(c.center[a])) {
      throw InvalidArgument("region: a sphere needs a finite 'center'");
    }
  }
  if (c.shape == Collider::Shape::Sphere && !finite_positive(c.radius))
    throw InvalidArgument("region: a sphere needs a finite 'radius' > 0, got " + format_real(c.radius));
  model.colliders.push_back(c);
}

void State::append(const Scalar* x0, const Scalar* v0, Index m, const Scalar* mass0, const Scalar* volume0,
                   Index material_code, Scalar youngs_modulus0, Scalar poisson_ratio0) {
  const int d = dim;
  if (!user_ordered()) throw InvalidArgument("state: append needs the rows in user order (Solver::user_order)");
  x.insert(x.end(), x0, x0 + m * d);
  v.insert(v.end(), v0, v0 + m * d);
  for (Index p = 0; p < m; ++p)
    for (int r = 0; r < d; ++r)
      for (int c = 0; c < d; ++c) F.push_back(r == c ? 1.0 : 0.0);
  C.resize(C.size() + static_cast<size_t>(m * d * d), 0.0);
  mass.insert(mass.end(), mass0, mass0 + m);
  volume.insert(volume.end(), volume0, volume0 + m);
  material.resize(material.size() + static_cast<size_t>(m), material_code);
  Jp.resize(Jp.size() + static_cast<size_t>(m), 1.0);
  youngs_modulus.resize(youngs_modulus.size() + static_cast<size_t>(m), youngs_modulus0);
  poisson_ratio.resize(poisson_ratio.size() + static_cast<size_t>(m), poisson_ratio0);
  n += m;
  binning = 0;
}

}  // namespace kinema::mpm
