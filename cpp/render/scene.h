// The scene model of the path tracer: materials, spheres (particles), triangle meshes and
// infinite planes, plus the closest-hit query. Spheres and triangles share one BVH (geometry/bvh.h);
// planes, which have no bounds, are tested one by one after it.
//
// Primitive ids: spheres 0..S-1, then triangles S..S+T-1, then planes S+T..S+T+P-1, in the order
// they were added. Geometry is copied in (a scene is built once per frame); add_* validate their
// input and throw InvalidArgument naming the argument.
#pragma once

#include <array>
#include <memory>
#include <vector>

#include "geometry/bvh.h"
#include "render/kernels.h"

namespace kinema::render {

using geometry::Bvh;
using geometry::hit_box;

enum class MaterialKind { lambertian, metal, dielectric };

// Lambertian: f = albedo / pi. Metal: mirror reflection perturbed by fuzz * (a point of the unit
// ball), times albedo; directions pushed below the surface are absorbed (Shirley). Dielectric:
// clear glass of index ior in vacuum, Fresnel-Schlick reflection, Snell refraction, no
// absorption unless `absorption` is set: Beer-Lambert attenuation exp(-absorption t) over the
// length t a path travels inside (coloured glass, water). Any material may also emit (two-sided)
// radiance `emission`.
struct Material {
  MaterialKind kind = MaterialKind::lambertian;
  Color albedo = Color::Constant(0.5);
  Scalar fuzz = 0;
  Scalar ior = 1.5;
  Color emission = Color::Zero();
  Color absorption = Color::Zero();  // [1/length], dielectrics only
};

// The closest hit along a ray: t, the primitive, its material, and the unit geometric normal
// turned against the ray (front_face says whether it was the outward normal).
struct Hit {
  Scalar t = kInfinity;
  Index primitive = -1;
  Index material = -1;
  Vec3 normal = Vec3::Zero();
  bool front_face = true;
};

// Closest-hit rays start a little off the surface they leave: this far in t, relative to the
// scene's size (a few hundred ulps of the largest coordinate).
constexpr Scalar kRayEpsilon = 1e-10;

class Scene {
 public:
  Index add_material(const Material& material);
  // centers: 3n values, radii: n values (> 0).
  void add_spheres(const Scalar* centers, const Scalar* radii, Index n, Index material);
  // vertices: 3m values, triangles: 3k vertex indices in [0, m).
  void add_mesh(const Scalar* vertices, Index m, const Index* triangles, Index k, Index material);
  void add_plane(const Vec3& point, const Vec3& normal, Index material);

  Index sphere_count() const { return static_cast<Index>(spheres_.size()); }
  Index triangle_count() const { return static_cast<Index>(triangles_.size()); }
  Index plane_count() const { return static_cast<Index>(planes_.size()); }
  Index primitive_count() const { return sphere_count() + triangle_count() + plane_count(); }
  const Material& material(Index id) const { return materials_[static_cast<size_t>(id)]; }
  Index material_of(Index primitive) const;

  // Builds the BVH over spheres and triangles if the geometry changed since the last build.
  // Not thread-safe; call before tracing in parallel. Returns the build time [s] (0 if cached).
  Scalar prepare();
  const Bvh& bvh() const { return *bvh_; }

  // Closest hit in (t_min, t_max) through the BVH (prepare() first), or by testing every
  // primitive (brute force; the reference of the tests). Both return the same t and primitive.
  Hit intersect(const Ray& ray, Scalar t_min, Scalar t_max) const;
  Hit intersect_brute_force(const Ray& ray, Scalar t_min, Scalar t_max) const;

  // Largest absolute coordinate of the geometry's bounds (planes' points included), >= 1.
  Scalar scale() const { return scale_; }

  // For the preview: the raw geometry.
  struct Sphere {
    Vec3 center;
    Scalar radius;
    Index material;
  };
  struct Triangle {
    Vec3 v0, e1, e2;  // vertices v0, v0 + e1, v0 + e2
    Index material;
  };
  struct Plane {
    Vec3 point, normal;  // unit normal
    Index material;
  };
  const std::vector<Sphere>& spheres() const { return spheres_; }
  const std::vector<Triangle>& triangles() const { return triangles_; }
  const std::vector<Plane>& planes() const { return planes_; }

  // t of primitive `id`'s hit in (t_min, t_max), or kInfinity.
  Scalar intersect_primitive(Index id, const Ray& ray, Scalar t_min, Scalar t_max) const;
  // Fills hit.normal and hit.front_face for the point at hit.t.
  void finish_hit(const Ray& ray, Hit& hit) const;

 private:
  // The closest hit among primitives [first, last) in (t_min, t_max), or `best` (hit at t_max)
  // when none is closer.
  Hit closest(Index first, Index last, const Ray& ray, Scalar t_min, Scalar t_max, Index best) const;
  void check_material(Index material, const char* name) const;
  void grow_scale(const Vec3& p);

  std::vector<Material> materials_;
  std::vector<Sphere> spheres_;
  std::vector<Triangle> triangles_;
  std::vector<Plane> planes_;
  std::unique_ptr<Bvh> bvh_;
  bool dirty_ = true;
  Scalar scale_ = 1;
};

}  // namespace kinema::render
