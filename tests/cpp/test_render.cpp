// Path tracer kernels: ray/primitive intersection against closed forms, the sampling densities
// (normalisation and moments), Snell's law and the limits of Schlick's approximation, the BVH
// on degenerate inputs against brute force, and the pixel loop's reproducibility.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include "core/parallel.h"
#include "render/camera.h"
#include "render/kernels.h"
#include "render/preview.h"
#include "render/scene.h"
#include "render/splat.h"
#include "render/tracer.h"

namespace kinema::render {

namespace {

Ray ray(Vec3 o, Vec3 d) { return Ray{o, d.normalized()}; }

Vec3 random_unit(std::mt19937_64& g) {
  std::normal_distribution<Scalar> n;
  return Vec3(n(g), n(g), n(g)).normalized();
}

}  // namespace

TEST(RenderKernels, SphereIntersection) {
  const Vec3 c(0, 0, -5);
  // Along the axis: near root at distance - r, far root from inside.
  EXPECT_DOUBLE_EQ(intersect_sphere(ray({0, 0, 0}, {0, 0, -1}), c, 1, 0, kInfinity), 4);
  EXPECT_DOUBLE_EQ(intersect_sphere(ray({0, 0, -5}, {0, 0, -1}), c, 1, 0, kInfinity), 1);
  EXPECT_DOUBLE_EQ(intersect_sphere(ray({0, 0, 0}, {0, 0, -1}), c, 1, 4.5, kInfinity), 6);
  EXPECT_EQ(intersect_sphere(ray({0, 0, 0}, {0, 0, 1}), c, 1, 0, kInfinity), kInfinity);
  EXPECT_EQ(intersect_sphere(ray({0, 1.001, 0}, {0, 0, -1}), c, 1, 0, kInfinity), kInfinity);
  EXPECT_EQ(intersect_sphere(ray({0, 0, 0}, {0, 0, -1}), c, 1, 0, 3.9), kInfinity);
  // Off-axis chord: hit where |(0, y, -t) - c| = r, t = 5 - sqrt(r^2 - y^2).
  EXPECT_NEAR(intersect_sphere(ray({0, 0.6, 0}, {0, 0, -1}), c, 1, 0, kInfinity), 5 - 0.8, 1e-15);
  // A tiny sphere far away keeps its digits (b^2 - c would cancel entirely here).
  const Scalar r = 1e-6, d = 1e4;
  const Scalar t = intersect_sphere(ray({0, 0.5e-6, 0}, {0, 0, -1}), Vec3(0, 0, -d), r, 0, kInfinity);
  EXPECT_NEAR(t, d - std::sqrt(r * r - 0.25e-12), 1e-12 * d);
}

TEST(RenderKernels, TriangleAndPlaneIntersection) {
  const Vec3 v0(0, 0, -2), e1(1, 0, 0), e2(0, 1, 0);
  EXPECT_DOUBLE_EQ(intersect_triangle(ray({0.25, 0.25, 0}, {0, 0, -1}), v0, e1, e2, 0, kInfinity), 2);
  EXPECT_DOUBLE_EQ(intersect_triangle(ray({0.25, 0.25, -4}, {0, 0, 1}), v0, e1, e2, 0, kInfinity), 2);
  EXPECT_EQ(intersect_triangle(ray({0.6, 0.6, 0}, {0, 0, -1}), v0, e1, e2, 0, kInfinity), kInfinity);
  EXPECT_EQ(intersect_triangle(ray({-0.1, 0.5, 0}, {0, 0, -1}), v0, e1, e2, 0, kInfinity), kInfinity);
  EXPECT_EQ(intersect_triangle(ray({0.2, 0.2, -2}, {1, 0, 0}), v0, e1, e2, 0, kInfinity), kInfinity);
  // Oblique hit: the hit point lies in the plane and inside the triangle.
  const Ray r = ray({1, 1, 1}, {-0.8, -0.7, -3});
  const Scalar t = intersect_triangle(r, v0, e1, e2, 0, kInfinity);
  ASSERT_LT(t, kInfinity);
  EXPECT_NEAR((r.origin + t * r.direction).z(), -2, 1e-14);
  EXPECT_NEAR(intersect_plane(ray({0, 3, 0}, {0, -1, 0}), Vec3(0, 1, 0), Vec3(0, 1, 0), 0, kInfinity), 2, 0);
  EXPECT_EQ(intersect_plane(ray({0, 3, 0}, {1, 0, 0}), Vec3(0, 1, 0), Vec3(0, 1, 0), 0, kInfinity), kInfinity);
  EXPECT_EQ(intersect_plane(ray({0, 3, 0}, {0, 1, 0}), Vec3(0, 1, 0), Vec3(0, 1, 0), 0, kInfinity), kInfinity);
}

TEST(RenderKernels, BoxSlabTest) {
  const Scalar lo[3] = {-1, -1, -1}, hi[3] = {1, 1, 1};
  auto inv = [](Vec3 d) { return Vec3(d.normalized().cwiseInverse()); };
  EXPECT_TRUE(hit_box(lo, hi, Vec3(0, 0, 5), inv({0, 0, -1}), 0, kInfinity));
  EXPECT_FALSE(hit_box(lo, hi, Vec3(0, 0, 5), inv({0, 0, 1}), 0, kInfinity));
  EXPECT_FALSE(hit_box(lo, hi, Vec3(0, 0, 5), inv({0, 0, -1}), 0, 3.9));
  EXPECT_TRUE(hit_box(lo, hi, Vec3(0, 0, 0), inv({1, 2, 3}), 0, kInfinity));  // from inside
  // Axis-parallel ray lying exactly in a slab plane (0 * inf = NaN must not reject it).
  EXPECT_TRUE(hit_box(lo, hi, Vec3(1, 0, 5), inv({0, 0, -1}), 0, kInfinity));
  EXPECT_FALSE(hit_box(lo, hi, Vec3(2, 0, 5), inv({0, 0, -1}), 0, kInfinity));
}

TEST(RenderKernels, CosineHemispherePdfIntegratesToOne) {
  // Midpoint rule in (theta, phi) of pdf(w) sin(theta) over the hemisphere.
  const int n = 2000;
  Scalar integral = 0;
  for (int i = 0; i < n; ++i) {
    const Scalar theta = (i + 0.5) * (kPi / 2) / n;
    integral += cosine_hemisphere_pdf(std::cos(theta)) * std::sin(theta) * (kPi / 2 / n) * 2 * kPi;
  }
  EXPECT_NEAR(integral, 1, 1e-6);
  EXPECT_EQ(cosine_hemisphere_pdf(-0.1), 0);
}

TEST(RenderKernels, CosineHemisphereSamplesFollowTheirPdf) {
  // Under pdf = cos / pi: P(cos theta <= c) = c^2, E[cos] = 2/3, E[cos^2] = 1/2, E[w_x] = 0;
  // checked by mean (5 standard errors) and by the Kolmogorov-Smirnov distance of cos theta.
  std::mt19937_64 g(1);
  std::uniform_real_distribution<Scalar> u;
  const Vec3 n = random_unit(g);
  const int m = 200000;
  std::vector<Scalar> cosines;
  Scalar sum_c = 0, sum_c2 = 0, sum_t = 0;
  Vec3 t, b;
  orthonormal_basis(n, t, b);
  for (int i = 0; i < m; ++i) {
    const Vec3 w = cosine_hemisphere(n, u(g), u(g));
    ASSERT_NEAR(w.norm(), 1, 1e-14);
    const Scalar c = w.dot(n);
    ASSERT_GE(c, 0);
    cosines.push_back(c);
    sum_c += c;
    sum_c2 += c * c;
    sum_t += w.dot(t);
  }
  const Scalar se_c = std::sqrt((0.5 - 4.0 / 9) / m), se_c2 = std::sqrt((1.0 / 3 - 0.25) / m);
  EXPECT_NEAR(sum_c / m, 2.0 / 3, 5 * se_c);
  EXPECT_NEAR(sum_c2 / m, 0.5, 5 * se_c2);
  EXPECT_NEAR(sum_t / m, 0, 5 * std::sqrt(0.25 / m));  // E[w_t^2] = (1 - E[c^2]) / 2
  std::sort(cosines.begin(), cosines.end());
  Scalar ks = 0;
  for (int i = 0; i < m; ++i) {
    const Scalar cdf = cosines[i] * cosines[i];
    ks = std::max({ks, std::abs(cdf - Scalar(i) / m), std::abs(cdf - Scalar(i + 1) / m)});
  }
  EXPECT_LT(ks, 1.95 / std::sqrt(Scalar(m)));  // 0.1% critical value
}

TEST(RenderKernels, OrthonormalBasisAndUniformBall) {
  std::mt19937_64 g(2);
  std::vector<Vec3> normals = {Vec3(0, 0, 1), Vec3(0, 0, -1), Vec3(1, 0, 0), Vec3(0, -1, 0)};
  for (int i = 0; i < 100; ++i) normals.push_back(random_unit(g));
  for (const Vec3& n : normals) {
    Vec3 t, b;
    orthonormal_basis(n, t, b);
    EXPECT_NEAR(t.norm(), 1, 1e-14);
    EXPECT_NEAR(b.norm(), 1, 1e-14);
    EXPECT_NEAR(t.dot(n), 0, 1e-14);
    EXPECT_NEAR(b.dot(n), 0, 1e-14);
    EXPECT_NEAR(t.dot(b), 0, 1e-14);
    EXPECT_NEAR(t.cross(b).dot(n), 1, 1e-14);  // right-handed
  }
  std::uniform_real_distribution<Scalar> u;
  const int m = 100000;
  Scalar r2 = 0;
  for (int i = 0; i < m; ++i) {
    const Vec3 p = uniform_ball(u(g), u(g), u(g));
    ASSERT_LE(p.norm(), 1);
    r2 += p.squaredNorm();
  }
  // Uniform in the ball: E|p|^2 = 3/5, Var |p|^2 = 3/7 - 9/25.
  EXPECT_NEAR(r2 / m, 0.6, 5 * std::sqrt((3.0 / 7 - 0.36) / m));
}

TEST(RenderKernels, ReflectionAndSnellRefraction) {
  std::mt19937_64 g(3);
  for (int i = 0; i < 200; ++i) {
    const Vec3 n = random_unit(g);
    Vec3 d = random_unit(g);
    if (d.dot(n) > 0) d = -d;
    const Vec3 r = reflect(d, n);
    EXPECT_NEAR(r.norm(), 1, 1e-14);
    EXPECT_NEAR(r.dot(n), -d.dot(n), 1e-14);               // angle of incidence = reflection
    EXPECT_NEAR((r - d).cross(n).norm(), 0, 1e-14);        // change along n only
    for (Scalar eta : {1 / 1.5, 1.5, 1 / 2.4, 1.0}) {
      const Scalar cos_i = -d.dot(n), sin_i = std::sqrt(std::max(Scalar(0), 1 - cos_i * cos_i));
      Vec3 t;
      Scalar cos_t = -1;
      const bool ok = refract(d, n, eta, t, cos_t);
      ASSERT_EQ(ok, eta * sin_i <= 1);
      if (!ok) continue;
      EXPECT_NEAR(t.norm(), 1, 1e-14);
      EXPECT_NEAR(-t.dot(n), cos_t, 1e-12);
      EXPECT_NEAR(std::sqrt(std::max(Scalar(0), 1 - cos_t * cos_t)), eta * sin_i, 1e-7);  // Snell
      EXPECT_NEAR(t.cross(n).cross(d.cross(n)).norm(), 0, 1e-12);  // stays in the incidence plane
    }
  }
}

TEST(RenderKernels, SchlickLimits) {
  const Scalar n = 1.5, r0 = 0.04;
  EXPECT_NEAR(schlick(1, 1, 1, n), r0, 1e-15);   // normal incidence
  EXPECT_NEAR(schlick(1, 1, n, 1), r0, 1e-15);   // same from inside
  EXPECT_NEAR(schlick(0, 0.7, 1, n), 1, 1e-15);  // grazing from outside
  EXPECT_NEAR(schlick(0.7, 0, n, 1), 1, 1e-15);  // at the critical angle from inside
  // Reciprocity: entering at theta_i and leaving along the reversed path give the same R.
  const Vec3 nrm(0, 0, 1);
  const Vec3 d = Vec3(0.6, 0, -0.8);
  Vec3 t, back;
  Scalar cos_t = 0, cos_back = 0;
  ASSERT_TRUE(refract(d, nrm, 1 / n, t, cos_t));
  ASSERT_TRUE(refract(-t, -nrm, n, back, cos_back));
  EXPECT_NEAR(schlick(0.8, cos_t, 1, n), schlick(cos_t, cos_back, n, 1), 1e-14);
  EXPECT_NEAR(cos_back, 0.8, 1e-14);
  // Monotone in the angle, within [R0, 1].
  Scalar last = 0;
  for (int i = 0; i <= 100; ++i) {
    const Scalar c = 1 - i / 100.0;
    const Scalar r = schlick(c, c, 1, n);
    EXPECT_GE(r, last);
    EXPECT_GE(r, r0 - 1e-15);
    EXPECT_LE(r, 1);
    last = r;
  }
}

TEST(RenderKernels, RngStreams) {
  Rng a(0, 5, 0), b(0, 5, 0), c(0, 6, 0), d(1, 5, 0), e(0, 5, 1);
  const Scalar x = a.uniform();
  EXPECT_EQ(x, b.uniform());
  EXPECT_NE(x, c.uniform());
  EXPECT_NE(x, d.uniform());
  EXPECT_NE(x, e.uniform());
  const int m = 100000;
  Scalar sum = 0, lo = 1, hi = 0;
  for (int i = 0; i < m; ++i) {
    const Scalar u = Rng(42, static_cast<std::uint64_t>(i), 0).uniform();  // first draw of each stream
    sum += u;
    lo = std::min(lo, u);
    hi = std::max(hi, u);
  }
  EXPECT_NEAR(sum / m, 0.5, 5 * std::sqrt(1.0 / 12 / m));
  EXPECT_GE(lo, 0);
  EXPECT_LT(hi, 1);
  EXPECT_EQ(roulette_survival(Color(0.2, 0.5, 0.1)), 0.5);
  EXPECT_EQ(roulette_survival(Color(3, 0.5, 0.1)), 1);
}

namespace {

// Every ray of a bundle from outside finds the same hit through the BVH and by brute force.
void expect_bvh_equals_brute_force(Scene& scene, unsigned seed, Scalar extent) {
  scene.prepare();
  std::mt19937_64 g(seed);
  std::uniform_real_distribution<Scalar> u(-extent, extent);
  int hits = 0;
  for (int i = 0; i < 3000; ++i) {
    const Vec3 o(u(g), u(g), u(g));
    const Ray r{o, (Vec3(u(g), u(g), u(g)) * 0.1 - o).normalized()};
    const Hit a = scene.intersect(r, 0, kInfinity), b = scene.intersect_brute_force(r, 0, kInfinity);
    ASSERT_EQ(a.primitive, b.primitive) << "ray " << i;
    ASSERT_EQ(a.t, b.t) << "ray " << i;
    hits += a.primitive >= 0;
  }
  EXPECT_GT(hits, 100);
}

}  // namespace

TEST(RenderBvh, CoincidentCentroidsSplitAtTheMedian) {
  Scene scene;
  const Index m = scene.add_material(Material{});
  std::vector<Scalar> c(3 * 1000, 0.0), r(1000);
  for (int i = 0; i < 1000; ++i) r[i] = 0.1 + 0.001 * i;  // concentric spheres
  scene.add_spheres(c.data(), r.data(), 1000, m);
  expect_bvh_equals_brute_force(scene, 4, 3);
  EXPECT_LE(scene.bvh().depth(), 12);
}

TEST(RenderBvh, ExponentialSpacingStaysShallow) {
  // Centres at 2^k: the SAH would peel one sphere per level; the depth limit bounds it.
  Scene scene;
  const Index m = scene.add_material(Material{});
  std::vector<Scalar> c, r;
  for (int k = 0; k < 300; ++k) {
    const Scalar x = std::pow(2.0, k / 8.0) * 1e-3;
    c.insert(c.end(), {x, 0, 0});
    r.push_back(0.05 * x);  // neighbours 9% of x apart: no overlap
  }
  scene.add_spheres(c.data(), r.data(), 300, m);
  EXPECT_LT(scene.prepare(), 1.0);
  EXPECT_LE(scene.bvh().depth(), Bvh::kMaxSahDepth + 12);
  for (int k = 0; k < 300; k += 7) {  // a ray straight down onto each sphere
    const Ray probe{Vec3(c[3 * k], 10 * r[k] + 1, 0), Vec3(0, -1, 0)};
    const Hit a = scene.intersect(probe, 0, kInfinity), b = scene.intersect_brute_force(probe, 0, kInfinity);
    EXPECT_EQ(a.primitive, k);
    EXPECT_EQ(b.primitive, k);
    EXPECT_EQ(a.t, b.t);
  }
}

TEST(RenderBvh, MixedSpheresAndTriangles) {
  Scene scene;
  const Index m = scene.add_material(Material{});
  std::mt19937_64 g(6);
  std::uniform_real_distribution<Scalar> u(-1, 1);
  std::vector<Scalar> c, r, v;
  std::vector<Index> tri;
  for (int i = 0; i < 500; ++i) {
    c.insert(c.end(), {u(g), u(g), u(g)});
    r.push_back(0.02 + 0.03 * (u(g) + 1));
    const Vec3 p(u(g), u(g), u(g));
    for (int k = 0; k < 3; ++k) v.insert(v.end(), {p.x() + 0.2 * u(g), p.y() + 0.2 * u(g), p.z() + 0.2 * u(g)});
    tri.insert(tri.end(), {3 * i, 3 * i + 1, 3 * i + 2});
  }
  scene.add_spheres(c.data(), r.data(), 500, m);
  scene.add_mesh(v.data(), 1500, tri.data(), 500, m);
  expect_bvh_equals_brute_force(scene, 7, 3);
}

TEST(RenderTracer, ImageIndependentOfThreadCount) {
  Scene scene;
  Material glass;
  glass.kind = MaterialKind::dielectric;
  const Index a = scene.add_material(Material{}), b = scene.add_material(glass);
  const Scalar c0[3] = {0, 0, 0}, c1[3] = {0.8, 0.3, 0}, r0 = 0.7, r1 = 0.4;
  scene.add_spheres(c0, &r0, 1, a);
  scene.add_spheres(c1, &r1, 1, b);
  Camera cam;
  cam.look_from = Vec3(0, 0.5, 3);
  cam.width = 24;
  cam.height = 17;
  RenderConfig cfg;
  cfg.samples_per_pixel = 3;
  Interrupt none;
  const int old = num_threads();
  set_num_threads(1);
  const RenderResult one = render(scene, cam, Sky{}, cfg, none);
  set_num_threads(2);
  const RenderResult two = render(scene, cam, Sky{}, cfg, none);
  set_num_threads(old);
  EXPECT_EQ(one.image, two.image);
  EXPECT_EQ(one.stats.rays, two.stats.rays);
  EXPECT_GT(one.stats.rays, cam.width * cam.height * 3);
}

// The splat's visible sphere per pixel is the preview's (a sphere in front of another hides it;
// the eye inside a sphere sees none of that sphere), its depth the preview's in float32.
TEST(RenderSplat, SameVisibleSphereAsThePreview) {
  std::mt19937_64 g(7);
  std::uniform_real_distribution<Scalar> u(-1, 1), r(0.02, 0.2);
  const Index n = 400;
  std::vector<Scalar> centers(3 * n), radii(n);
  for (Index i = 0; i < n; ++i) {
    for (int a = 0; a < 3; ++a) centers[static_cast<size_t>(3 * i + a)] = u(g);
    radii[static_cast<size_t>(i)] = r(g);
  }
  Scene scene;
  scene.add_spheres(centers.data(), radii.data(), n, scene.add_material(Material{}));
  Camera cam;
  cam.look_from = Vec3(0.3, 0.6, 3.5);
  cam.width = 48;
  cam.height = 36;
  Interrupt none;
  const PreviewResult ref = preview(scene, cam, Sky{}, PreviewConfig{}, none);
  const SplatResult s = splat_spheres(centers.data(), n, radii.data(), n, cam, none);
  Index hits = 0;
  for (size_t px = 0; px < s.ids.size(); ++px) {
    ASSERT_EQ(s.ids[px], ref.ids[px]) << "pixel " << px;
    if (s.ids[px] < 0) {
      EXPECT_TRUE(std::isinf(s.depth[px]));
      continue;
    }
    ++hits;
    EXPECT_NEAR(s.depth[px], ref.depth[px], 4e-7 * ref.depth[px]);
    const Scalar len = std::hypot(s.normal[3 * px], s.normal[3 * px + 1], s.normal[3 * px + 2]);
    EXPECT_NEAR(len, 1, 1e-6);
  }
  EXPECT_EQ(hits, s.hits);
  EXPECT_GT(hits, cam.width * cam.height / 4);
  // One shared radius; the eye inside the only sphere: nothing seen.
  const Scalar eye[3] = {0.3, 0.6, 3.5}, big = 1;
  const SplatResult inside = splat_spheres(eye, 1, &big, 1, cam, none);
  EXPECT_EQ(inside.hits, 0);
}

}  // namespace kinema::render
