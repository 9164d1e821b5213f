#include <cmath>
#include <string>

#include "core/errors.h"
#include "massspring/solver.h"
#include "mesh/vertex_set.h"

namespace kinema::massspring {

namespace {

void check_each(const std::vector<Scalar>& a, const char* name, bool positive, const char* item) {
  for (std::size_t s = 0; s < a.size(); ++s)
    if (!std::isfinite(a[s]) || (positive ? !(a[s] > 0) : !(a[s] >= 0)))
      throw InvalidArgument(std::string(name) + ": expected values " + (positive ? "> 0" : ">= 0") +
                            " and finite, got " + format_real(a[s]) + " at " + item + " " + std::to_string(s));
}

}  // namespace

void check_config(const Config& c) {
  if (!(std::isfinite(c.beta) && c.beta >= 0))
    throw InvalidArgument("beta: expected a finite number >= 0, got " + format_real(c.beta));
  if (!(std::isfinite(c.cg_tol) && c.cg_tol > 0))
    throw InvalidArgument("cg_tol: expected a finite number > 0, got " + format_real(c.cg_tol));
  if (!(std::isfinite(c.adjoint_tol) && c.adjoint_tol >= 0))
    throw InvalidArgument("adjoint_tol: expected a finite number >= 0, got " + format_real(c.adjoint_tol));
}

void check_parameters(const Model& m) {
  check_each(m.stiffness, "stiffness", false, "spring");
  check_each(m.rest_length, "rest_length", false, "spring");
  check_each(m.damping, "damping", false, "spring");
  check_each(m.mass, "mass", true, "vertex");
}

Model make_model(int dim, Index vertex_count, const Index* springs, Index spring_count,
                 const Scalar* stiffness, const Scalar* rest_length, const Scalar* damping,
                 const Scalar* mass, const Index* fixed, Index fixed_count,
                 const std::vector<Scalar>& gravity) {
  if (dim != 2 && dim != 3) throw InvalidArgument("x: expected d = 2 or 3 columns");
  Model m;
  m.dim = dim;
  m.vertex_count = vertex_count;
  m.spring_count = spring_count;
  m.springs.assign(springs, springs + 2 * spring_count);
  m.stiffness.assign(stiffness, stiffness + spring_count);
  m.rest_length.assign(rest_length, rest_length + spring_count);
  m.damping.assign(damping, damping + spring_count);
  m.mass.assign(mass, mass + vertex_count);
  check_parameters(m);
  m.fixed = vertex_flags(fixed, fixed_count, vertex_count, "fixed");
  bool any_gravity = false;
  if (!gravity.empty() && static_cast<int>(gravity.size()) != dim)
    throw InvalidArgument("gravity: expected " + std::to_string(dim) + " components");
  for (Scalar g : gravity) {
    if (!std::isfinite(g)) throw InvalidArgument("gravity: expected finite components");
    any_gravity = any_gravity || g != 0;
  }
  if (any_gravity) m.gravity = gravity;
  return m;
}

}  // namespace kinema::massspring
