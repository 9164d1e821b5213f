// Scene construction (validated) and the closest-hit query through the BVH or by brute force.
#include "render/scene.h"

#include <chrono>
#include <cmath>
#include <string>

#include "core/errors.h"

namespace kinema::render {

namespace {

bool finite(const Vec3& v) { return v.allFinite(); }

void check_color(const Color& c, const char* name, Scalar max) {
  if (!c.allFinite() || c.minCoeff() < 0 || c.maxCoeff() > max)
    throw InvalidArgument(std::string(name) + ": expected components in [0, " + format_real(max) +
                          "], got (" + format_real(c[0]) + ", " + format_real(c[1]) + ", " +
                          format_real(c[2]) + ")");
}

}  // namespace

Index Scene::add_material(const Material& m) {
  check_color(m.albedo, "albedo", 1);
  check_color(m.emission, "emission", kInfinity);
  if (!std::isfinite(m.fuzz) || m.fuzz < 0 || m.fuzz > 1)
    throw InvalidArgument("fuzz: expected a number in [0, 1], got " + format_real(m.fuzz));
  if (!std::isfinite(m.ior) || m.ior <= 0)
    throw InvalidArgument("ior: expected a finite index of refraction > 0, got " + format_real(m.ior));
  materials_.push_back(m);
  return static_cast<Index>(materials_.size()) - 1;
}

void Scene::check_material(Index material, const char* name) const {
  if (material < 0 || material >= static_cast<Index>(materials_.size()))
    throw InvalidArgument(std::string(name) + ": no material " + std::to_string(material));
}

void Scene::grow_scale(const Vec3& p) { scale_ = std::max(scale_, p.cwiseAbs().maxCoeff()); }

void Scene::add_spheres(const Scalar* centers, const Scalar* radii, Index n, Index material) {
  check_material(material, "material");
  for (Index i = 0; i < n; ++i) {
    const Vec3 c(centers[3 * i], centers[3 * i + 1], centers[3 * i + 2]);
    if (!finite(c)) throw InvalidArgument("centers: row " + std::to_string(i) + " is not finite");
    if (!std::isfinite(radii[i]) || radii[i] <= 0)
      throw InvalidArgument("radii: expected finite radii > 0, got " + format_real(radii[i]) +
                            " at row " + std::to_string(i));
  }
  spheres_.reserve(spheres_.size() + static_cast<size_t>(n));
  for (Index i = 0; i < n; ++i) {
    const Vec3 c(centers[3 * i], centers[3 * i + 1], centers[3 * i + 2]);
    spheres_.push_back(Sphere{c, radii[i], material});
    grow_scale(c.array().abs().matrix() + Vec3::Constant(radii[i]));
  }
  dirty_ = true;
}

void Scene::add_mesh(const Scalar* vertices, Index m, const Index* triangles, Index k, Index material) {
  check_material(material, "material");
  for (Index i = 0; i < 3 * m; ++i)
    if (!std::isfinite(vertices[i]))
      throw InvalidArgument("vertices: row " + std::to_string(i / 3) + " is not finite");
  for (Index i = 0; i < 3 * k; ++i)
    if (triangles[i] < 0 || triangles[i] >= m)
      throw InvalidArgument("triangles: vertex index " + std::to_string(triangles[i]) + " in row " +
                            std::to_string(i / 3) + " is outside [0, " + std::to_string(m) + ")");
  auto vertex = [&](Index v) { return Vec3(vertices[3 * v], vertices[3 * v + 1], vertices[3 * v + 2]); };
  triangles_.reserve(triangles_.size() + static_cast<size_t>(k));
  for (Index i = 0; i < k; ++i) {
    const Vec3 a = vertex(triangles[3 * i]), b = vertex(triangles[3 * i + 1]), c = vertex(triangles[3 * i + 2]);
    triangles_.push_back(Triangle{a, b - a, c - a, material});
    grow_scale(a);
    grow_scale(b);
    grow_scale(c);
  }
  dirty_ = true;
}

void Scene::add_plane(const Vec3& point, const Vec3& normal, Index material) {
  check_material(material, "material");
  if (!finite(point)) throw InvalidArgument("point: expected finite coordinates");
  const Scalar len = normal.norm();
  if (!std::isfinite(len) || len == 0)
    throw InvalidArgument("normal: expected a finite non-zero vector");
  planes_.push_back(Plane{point, normal / len, material});
  grow_scale(point);
}

Index Scene::material_of(Index id) const {
  const Index s = sphere_count(), t = triangle_count();
  if (id < s) return spheres_[static_cast<size_t>(id)].material;
  if (id < s + t) return triangles_[static_cast<size_t>(id - s)].material;
  return planes_[static_cast<size_t>(id - s - t)].material;
}

Scalar Scene::prepare() {
  if (!dirty_ && bvh_) return 0;
  const auto start = std::chrono::steady_clock::now();
  const size_t s = spheres_.size(), n = s + triangles_.size();
  std::vector<Scalar> lo(3 * n), hi(3 * n);
  for (size_t i = 0; i < s; ++i)
    for (int a = 0; a < 3; ++a) {
      lo[3 * i + a] = spheres_[i].center[a] - spheres_[i].radius;
      hi[3 * i + a] = spheres_[i].center[a] + spheres_[i].radius;
    }
  for (size_t i = 0; i < triangles_.size(); ++i) {
    const Triangle& tri = triangles_[i];
    const Vec3 b = tri.v0 + tri.e1, c = tri.v0 + tri.e2;
    for (int a = 0; a < 3; ++a) {
      lo[3 * (s + i) + a] = std::min({tri.v0[a], b[a], c[a]});
      hi[3 * (s + i) + a] = std::max({tri.v0[a], b[a], c[a]});
    }
  }
  bvh_ = std::make_unique<Bvh>(lo, hi);
  dirty_ = false;
  return std::chrono::duration<Scalar>(std::chrono::steady_clock::now() - start).count();
}

Scalar Scene::intersect_primitive(Index id, const Ray& ray, Scalar t_min, Scalar t_max) const {
  const Index s = sphere_count(), t = triangle_count();
  if (id < s) {
    const Sphere& sp = spheres_[static_cast<size_t>(id)];
    return intersect_sphere(ray, sp.center, sp.radius, t_min, t_max);
  }
  if (id < s + t) {
    const Triangle& tri = triangles_[static_cast<size_t>(id - s)];
    return intersect_triangle(ray, tri.v0, tri.e1, tri.e2, t_min, t_max);
  }
  const Plane& p = planes_[static_cast<size_t>(id - s - t)];
  return intersect_plane(ray, p.point, p.normal, t_min, t_max);
}

void Scene::finish_hit(const Ray& ray, Hit& hit) const {
  const Index s = sphere_count(), t = triangle_count(), id = hit.primitive;
  Vec3 n;
  if (id < s) {
    const Sphere& sp = spheres_[static_cast<size_t>(id)];
    n = (ray.origin + hit.t * ray.direction - sp.center).normalized();
  } else if (id < s + t) {
    const Triangle& tri = triangles_[static_cast<size_t>(id - s)];
    n = tri.e1.cross(tri.e2).normalized();
  } else {
    n = planes_[static_cast<size_t>(id - s - t)].normal;
  }
  hit.material = material_of(id);
  hit.front_face = ray.direction.dot(n) < 0;
  hit.normal = hit.front_face ? n : Vec3(-n);
}

Hit Scene::closest(Index first, Index last, const Ray& ray, Scalar t_min, Scalar t_max,
                   Index best) const {
  for (Index id = first; id < last; ++id) {
    const Scalar t = intersect_primitive(id, ray, t_min, t_max);
    if (t < t_max) {
      t_max = t;
      best = id;
    }
  }
  Hit hit;
  if (best >= 0) {
    hit.t = t_max;
    hit.primitive = best;
    finish_hit(ray, hit);
  }
  return hit;
}

Hit Scene::intersect(const Ray& ray, Scalar t_min, Scalar t_max) const {
  Index best = -1;
  const std::vector<Index>& order = bvh_->order();
  t_max = bvh_->traverse(ray.origin, ray.direction, t_min, t_max,
                         [&](std::int32_t first, std::int32_t count, Scalar t_far) {
                           for (std::int32_t i = first; i < first + count; ++i) {
                             const Index id = order[static_cast<size_t>(i)];
                             const Scalar t = intersect_primitive(id, ray, t_min, t_far);
                             if (t < t_far) {
                               t_far = t;
                               best = id;
                             }
                           }
                           return t_far;
                         });
  // Planes have no bounds: tested after the BVH, against its closest hit.
  return closest(sphere_count() + triangle_count(), primitive_count(), ray, t_min, t_max, best);
}

Hit Scene::intersect_brute_force(const Ray& ray, Scalar t_min, Scalar t_max) const {
  return closest(0, primitive_count(), ray, t_min, t_max, -1);
}

}  // namespace kinema::render
