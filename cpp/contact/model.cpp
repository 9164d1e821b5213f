// Building the contact model: validation, lumped masses, rest shapes and the collision mesh.
#include "contact/model.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <map>

#include "core/errors.h"

namespace kinema::contact {

namespace {

void check_indices(const Index* idx, Index count, Index n, const char* name) {
  for (Index k = 0; k < count; ++k)
    if (idx[k] < 0 || idx[k] >= n)
      throw InvalidArgument(std::string(name) + ": index " + std::to_string(idx[k]) + " at entry " +
                            std::to_string(k) + " is outside [0, " + std::to_string(n) + ")");
}

void check_positive(Scalar v, const char* name) {
  if (!(std::isfinite(v) && v > 0))
    throw InvalidArgument(std::string(name) + ": expected a finite value > 0, got " + format_real(v));
}

}  // namespace

Index Model::append_vertices(const Scalar* x, Index n, const char* name) {
  if (n <= 0) throw InvalidArgument(std::string(name) + ": expected at least one vertex");
  for (Index k = 0; k < 3 * n; ++k)
    if (!std::isfinite(x[k])) throw InvalidArgument(std::string(name) + ": contains non-finite values");
  const Index start = vertex_count;
  rest.insert(rest.end(), x, x + 3 * n);
  mass.resize(static_cast<size_t>(start + n), 0);
  fixed.resize(static_cast<size_t>(start + n), 0);
  driven.resize(static_cast<size_t>(start + n), 0);
  damping.resize(static_cast<size_t>(start + n), 0);
  body.resize(static_cast<size_t>(start + n), body_count);
  body_friction.push_back(-1);
  vertex_count += n;
  ++body_count;
  return start;
}

void Model::add_surface(const std::vector<Index>& triangles) {
  std::vector<std::array<Index, 2>> new_edges;
  for (size_t f = 0; f < triangles.size(); f += 3) {
    for (int k = 0; k < 3; ++k) {
      const Index a = triangles[f + k], b = triangles[f + (k + 1) % 3];
      new_edges.push_back({std::min(a, b), std::max(a, b)});
    }
  }
  std::sort(new_edges.begin(), new_edges.end());
  new_edges.erase(std::unique(new_edges.begin(), new_edges.end()), new_edges.end());
  faces.insert(faces.end(), triangles.begin(), triangles.end());
  for (const auto& e : new_edges) edges.insert(edges.end(), e.begin(), e.end());
  std::vector<Index> used(triangles);
  std::sort(used.begin(), used.end());
  used.erase(std::unique(used.begin(), used.end()), used.end());
  points.insert(points.end(), used.begin(), used.end());
}

Index Model::add_solid(const Scalar* x, Index n, const Index* elements, Index m, fem::Material material,
                       const Scalar* youngs_modulus, const Scalar* poisson_ratio, Index param_count,
                       Scalar density, Scalar damping_coefficient, const Index* fixed_ids, Index fixed_count) {
  if (m <= 0) throw InvalidArgument("tets: expected at least one tetrahedron");
  if (param_count != 1 && param_count != m)
    throw InvalidArgument("youngs_modulus, poisson_ratio: expected 1 or " + std::to_string(m) + " values, got " +
                          std::to_string(param_count));
  for (Index k = 0; k < param_count; ++k) {
    check_positive(youngs_modulus[k], "youngs_modulus");
    if (!(poisson_ratio[k] > -1 && poisson_ratio[k] < 0.5))
      throw InvalidArgument("poisson_ratio: expected a value in (-1, 0.5), got " + format_real(poisson_ratio[k]));
  }
  check_positive(density, "density");
  if (!(std::isfinite(damping_coefficient) && damping_coefficient >= 0))
    throw InvalidArgument("damping: expected a finite value >= 0, got " + format_real(damping_coefficient));
  check_indices(elements, 4 * m, n, "tets");
  check_indices(fixed_ids, fixed_count, n, "fixed");
  // Every check before the model changes, so a refused body leaves the scene as it was.
  for (Index e = 0; e < m; ++e) {
    fem::Mat<3> dm_inv;
    const Scalar vol = fem::rest_shape<3>(x, &elements[4 * e], dm_inv);
    if (!(vol > 0))
      throw InvalidArgument("tets: tetrahedron " + std::to_string(e) +
                            " is inverted or degenerate in the rest shape (signed volume " + format_real(vol) +
                            "); expected positively oriented elements");
  }
  const Index start = append_vertices(x, n, "vertices");
  for (Index i = start; i < start + n; ++i) damping[static_cast<size_t>(i)] = damping_coefficient;
  std::map<std::array<Index, 3>, std::pair<int, std::array<Index, 3>>> face_count;
  for (Index e = 0; e < m; ++e) {
    Index t[4];
    for (int a = 0; a < 4; ++a) t[a] = start + elements[4 * e + a];
    fem::Mat<3> dm_inv;
    const Scalar vol = fem::rest_shape<3>(rest.data(), t, dm_inv);
    const Index k = param_count == 1 ? 0 : e;
    Scalar mu, lam;
    fem::lame(youngs_modulus[k], poisson_ratio[k], mu, lam);
    tets.insert(tets.end(), t, t + 4);
    tet_dm_inv.push_back(dm_inv);
    tet_volume.push_back(vol);
    tet_mu.push_back(mu);
    tet_lambda.push_back(lam);
    tet_material.push_back(material);
    for (int a = 0; a < 4; ++a) mass[static_cast<size_t>(t[a])] += density * vol / 4;
    // Faces with outward orientation for a positively oriented tet.
    static const int kFace[4][3] = {{1, 2, 3}, {0, 3, 2}, {0, 1, 3}, {0, 2, 1}};
    for (const auto& f : kFace) {
      std::array<Index, 3> tri{t[f[0]], t[f[1]], t[f[2]]};
      std::array<Index, 3> key = tri;
      std::sort(key.begin(), key.end());
      auto& slot = face_count[key];
      ++slot.first;
      slot.second = tri;
    }
  }
  std::vector<Index> boundary;
  for (const auto& [key, value] : face_count)
    if (value.first == 1) boundary.insert(boundary.end(), value.second.begin(), value.second.end());
  add_surface(boundary);
  for (Index k = 0; k < fixed_count; ++k) fixed[static_cast<size_t>(start + fixed_ids[k])] = 1;
  return start;
}

Index Model::add_cloth(const Scalar* x, Index n, const Index* triangles, Index m, const Index* spring_ids,
                       Index spring_count, Scalar stiffness, Scalar density, const Index* fixed_ids,
                       Index fixed_count) {
  check_positive(stiffness, "stiffness");
  check_positive(density, "density");
  if (m <= 0) throw InvalidArgument("triangles: expected at least one triangle");
  check_indices(triangles, 3 * m, n, "triangles");
  check_indices(spring_ids, 2 * spring_count, n, "springs");
  check_indices(fixed_ids, fixed_count, n, "fixed");
  for (Index f = 0; f < m; ++f) {
    const Vec3 a = Eigen::Map<const Vec3>(x + 3 * triangles[3 * f]);
    const Vec3 b = Eigen::Map<const Vec3>(x + 3 * triangles[3 * f + 1]);
    const Vec3 c = Eigen::Map<const Vec3>(x + 3 * triangles[3 * f + 2]);
    if (!((b - a).cross(c - a).norm() > 0))
      throw InvalidArgument("triangles: triangle " + std::to_string(f) + " has zero area in the rest shape");
  }
  for (Index s = 0; s < spring_count; ++s)
    if (spring_ids[2 * s] == spring_ids[2 * s + 1])
      throw InvalidArgument("springs: spring " + std::to_string(s) + " joins a vertex to itself");
  const Index start = append_vertices(x, n, "vertices");
  std::vector<Index> tris(triangles, triangles + 3 * m);
  for (Index& v : tris) v += start;
  for (Index f = 0; f < m; ++f) {
    const Vec3 a = Eigen::Map<const Vec3>(&rest[3 * tris[3 * f]]);
    const Vec3 b = Eigen::Map<const Vec3>(&rest[3 * tris[3 * f + 1]]);
    const Vec3 c = Eigen::Map<const Vec3>(&rest[3 * tris[3 * f + 2]]);
    const Scalar area = (b - a).cross(c - a).norm() / 2;
    for (int k = 0; k < 3; ++k) mass[static_cast<size_t>(tris[3 * f + k])] += density * area / 3;
  }
  for (Index s = 0; s < spring_count; ++s) {
    const Index i = start + spring_ids[2 * s], j = start + spring_ids[2 * s + 1];
    springs.push_back(i);
    springs.push_back(j);
    spring_stiffness.push_back(stiffness);
    spring_damping.push_back(0);
    const Vec3 d = Eigen::Map<const Vec3>(&rest[3 * j]) - Eigen::Map<const Vec3>(&rest[3 * i]);
    spring_rest.push_back(d.norm());
  }
  add_surface(tris);
  for (Index k = 0; k < fixed_count; ++k) fixed[static_cast<size_t>(start + fixed_ids[k])] = 1;
  return start;
}

Index Model::add_springs(const Scalar* x, Index n, const Index* spring_ids, Index spring_count,
                         const Scalar* stiffness, const Scalar* rest_length, const Scalar* spring_damping_values,
                         const Scalar* masses, const Index* triangles, Index m, const Index* fixed_ids,
                         Index fixed_count) {
  check_indices(spring_ids, 2 * spring_count, n, "springs");
  check_indices(triangles, 3 * m, n, "triangles");
  check_indices(fixed_ids, fixed_count, n, "fixed");
  for (Index s = 0; s < spring_count; ++s) {
    if (spring_ids[2 * s] == spring_ids[2 * s + 1])
      throw InvalidArgument("springs: spring " + std::to_string(s) + " joins a vertex to itself");
    if (!(std::isfinite(stiffness[s]) && stiffness[s] >= 0))
      throw InvalidArgument("stiffness: expected finite values >= 0, got " + format_real(stiffness[s]));
    if (!(std::isfinite(rest_length[s]) && rest_length[s] >= 0))
      throw InvalidArgument("rest_length: expected finite values >= 0, got " + format_real(rest_length[s]));
    if (!(std::isfinite(spring_damping_values[s]) && spring_damping_values[s] >= 0))
      throw InvalidArgument("damping: expected finite values >= 0, got " + format_real(spring_damping_values[s]));
  }
  for (Index i = 0; i < n; ++i) check_positive(masses[i], "mass");
  const Index start = append_vertices(x, n, "vertices");
  for (Index i = 0; i < n; ++i) mass[static_cast<size_t>(start + i)] = masses[i];
  for (Index s = 0; s < spring_count; ++s) {
    springs.push_back(start + spring_ids[2 * s]);
    springs.push_back(start + spring_ids[2 * s + 1]);
    spring_stiffness.push_back(stiffness[s]);
    spring_rest.push_back(rest_length[s]);
    spring_damping.push_back(spring_damping_values[s]);
  }
  if (m > 0) {
    std::vector<Index> tris(triangles, triangles + 3 * m);
    for (Index& v : tris) v += start;
    add_surface(tris);
  } else {
    for (Index i = start; i < start + n; ++i) points.push_back(i);
  }
  for (Index k = 0; k < fixed_count; ++k) fixed[static_cast<size_t>(start + fixed_ids[k])] = 1;
  return start;
}

namespace {

void check_friction(Scalar friction) {
  if (std::isnan(friction) || std::isinf(friction))
    throw InvalidArgument("friction: expected a finite value >= 0, got " + format_real(friction));
}

}  // namespace

Index Model::add_obstacle(const Scalar* x, Index n, const Index* triangles, Index m, bool moving, Scalar friction) {
  if (m <= 0) throw InvalidArgument("triangles: expected at least one triangle");
  check_indices(triangles, 3 * m, n, "triangles");
  check_friction(friction);
  const Index start = append_vertices(x, n, "vertices");
  body_friction.back() = friction;
  for (Index k = start; k < start + n; ++k) fixed[static_cast<size_t>(k)] = 1, driven[static_cast<size_t>(k)] = moving;
  std::vector<Index> tris(triangles, triangles + 3 * m);
  for (Index& v : tris) v += start;
  add_surface(tris);
  return start;
}

Index Model::add_plane(const Vec3& point, const Vec3& normal, Scalar friction, bool moving) {
  const Scalar len = normal.norm();
  if (!(std::isfinite(len) && len > 0)) throw InvalidArgument("normal: expected a finite non-zero vector");
  if (!point.allFinite()) throw InvalidArgument("point: contains non-finite values");
  check_friction(friction);
  Index vertex = -1;
  if (moving) {
    // A driven vertex that is no collision primitive: it only carries the plane's point.
    vertex = append_vertices(point.data(), 1, "point");
    body_friction.back() = friction;
    fixed[static_cast<size_t>(vertex)] = 1;
    driven[static_cast<size_t>(vertex)] = 1;
  }
  planes.push_back({point, normal / len, friction, vertex});
  return vertex;
}

Scalar Model::total_mass() const {
  Scalar m = 0;
  for (Scalar w : mass) m += w;
  return m;
}

Scalar Model::bbox_diagonal(const Scalar* x) const {
  Vec3 lo = Vec3::Constant(std::numeric_limits<Scalar>::infinity()), hi = -lo;
  // A moving plane's point is not part of the scene's extent (a static plane's is not either).
  auto plane_point = [&](Index i) {
    for (const Plane& p : planes)
      if (p.vertex == i) return true;
    return false;
  };
  for (Index i = 0; i < vertex_count; ++i) {
    if (driven[static_cast<size_t>(i)] && plane_point(i)) continue;
    const Vec3 p = Eigen::Map<const Vec3>(x + 3 * i);
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  return (hi.array() >= lo.array()).all() ? (hi - lo).norm() : 0;
}

State make_state(const Model& model) {
  State s;
  s.x = model.rest;
  s.v.assign(model.rest.size(), 0);
  s.target = model.rest;
  return s;
}

}  // namespace kinema::contact
