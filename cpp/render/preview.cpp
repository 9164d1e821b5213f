// The z-buffered splatter/rasteriser behind render::preview.
#include "render/preview.h"

#include <omp.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <string>

#include "core/errors.h"
#include "render/camera.h"
#include "render/projection.h"

namespace kinema::render {

namespace {

using detail::bin_to_bands;
using detail::kBandRows;
using detail::PixelBox;
using detail::Projector;

PixelBox sphere_box(const Projector& p, const Scene::Sphere& s) { return detail::sphere_box(p, s.center, s.radius); }

// Primitives reaching closer than this to the eye plane (or behind it) get the whole image.
constexpr Scalar kNearFraction = 1e-9;

PixelBox triangle_box(const Projector& p, const Scene::Triangle& t, Scalar scale) {
  const Vec3 v[3] = {p.to_camera(t.v0), p.to_camera(t.v0 + t.e1), p.to_camera(t.v0 + t.e2)};
  const Scalar z_lo = std::min({v[0].z(), v[1].z(), v[2].z()});
  if (std::max({v[0].z(), v[1].z(), v[2].z()}) <= 0) return PixelBox{};
  if (z_lo <= kNearFraction * scale) return p.whole();
  // The projection of a triangle in front of the eye is the triangle of its projected vertices.
  Scalar x_lo = kInfinity, x_hi = -kInfinity, y_lo = kInfinity, y_hi = -kInfinity;
  for (const Vec3& q : v) {
    x_lo = std::min(x_lo, q.x() / q.z());
    x_hi = std::max(x_hi, q.x() / q.z());
    y_lo = std::min(y_lo, q.y() / q.z());
    y_hi = std::max(y_hi, q.y() / q.z());
  }
  const Scalar pad = 1e-12 * (1 + std::max({std::abs(x_lo), std::abs(x_hi), std::abs(y_lo), std::abs(y_hi)}));
  return p.box(x_lo - pad, x_hi + pad, y_lo - pad, y_hi + pad);
}

// Fraction of the light's disc (angular radius `radius` around the unit direction l) seen from
// p: `samples` rays to a Fibonacci spiral of points on the disc (Vogel 1979: even coverage for
// any count), turned by an angle hashed from the pixel so that the sampling pattern does not
// band; deterministic for any thread count.
Scalar light_visibility(const Scene& scene, const Vec3& p, const Vec3& l, Scalar radius, Index samples,
                        Scalar t_min, std::uint64_t pixel) {
  if (samples <= 0) return 1;
  const Vec3 a = std::abs(l.x()) < 0.9 ? Vec3(1, 0, 0) : Vec3(0, 1, 0);
  const Vec3 u = l.cross(a).normalized(), w = l.cross(u);
  const Scalar spread = std::tan(radius);
  const Scalar turn = static_cast<Scalar>(splitmix64(pixel) >> 11) * 0x1.0p-53 * 2 * kPi;
  constexpr Scalar golden = 2.39996322972865332;  // pi (3 - sqrt 5)
  Index seen = 0;
  for (Index k = 0; k < samples; ++k) {
    const Scalar rho = spread * std::sqrt((static_cast<Scalar>(k) + 0.5) / static_cast<Scalar>(samples));
    const Scalar phi = turn + golden * static_cast<Scalar>(k);
    const Vec3 d = (l + rho * (std::cos(phi) * u + std::sin(phi) * w)).normalized();
    if (scene.intersect(Ray{p, d}, t_min, kInfinity).primitive < 0) ++seen;
  }
  return static_cast<Scalar>(seen) / static_cast<Scalar>(samples);
}

}  // namespace

PreviewResult preview(const Scene& scene, const Camera& camera, const Sky& sky,
                      const PreviewConfig& config, Interrupt& interrupt) {
  validate(camera);
  if (!config.light.allFinite() || config.light.norm() == 0)
    throw InvalidArgument("light: expected a finite non-zero direction");
  if (!(config.ambient >= 0 && config.ambient <= 1))
    throw InvalidArgument("ambient: expected a number in [0, 1], got " + format_real(config.ambient));
  if (!(config.specular >= 0 && std::isfinite(config.specular)))
    throw InvalidArgument("specular: expected a finite number >= 0, got " + format_real(config.specular));
  if (!(config.shininess > 0 && std::isfinite(config.shininess)))
    throw InvalidArgument("shininess: expected a finite number > 0, got " + format_real(config.shininess));
  if (config.shadow_samples < 0)
    throw InvalidArgument("shadow_samples: expected an integer >= 0, got " + std::to_string(config.shadow_samples));
  if (!(config.light_radius >= 0 && config.light_radius < 1.5))
    throw InvalidArgument("light_radius: expected an angle in [0, 1.5) rad, got " + format_real(config.light_radius));
  const CameraFrame frame(camera);
  const Projector projector(frame);
  const Index width = camera.width, height = camera.height;
  const Index s_count = scene.sphere_count(), bounded = s_count + scene.triangle_count();
  const Scalar scale = scene.scale(), t_min = kRayEpsilon * scale;

  // Pixel boxes of all bounded primitives, then a counting sort of the primitives into bands.
  // near[i]: no hit of primitive i is closer than this (|c - eye| - r for a sphere, shrunk by far
  // more than its rounding; 0 for triangles), so pixels already holding a nearer hit skip it.
  std::vector<PixelBox> boxes(static_cast<size_t>(bounded));
  std::vector<Scalar> near(static_cast<size_t>(bounded), 0);
#pragma omp parallel for schedule(static)
  for (Index i = 0; i < bounded; ++i) {
    if (i < s_count) {
      const Scene::Sphere& sp = scene.spheres()[static_cast<size_t>(i)];
      boxes[static_cast<size_t>(i)] = sphere_box(projector, sp);
      near[static_cast<size_t>(i)] = ((sp.center - frame.origin()).norm() - sp.radius) * (1 - 1e-9);
    } else {
      boxes[static_cast<size_t>(i)] =
          triangle_box(projector, scene.triangles()[static_cast<size_t>(i - s_count)], scale);
    }
  }
  const Index bands = (height + kBandRows - 1) / kBandRows;
  std::vector<Index> start, members;
  bin_to_bands(boxes, height, start, members);
  interrupt.check();

  PreviewResult out;
  const auto pixels = static_cast<size_t>(width * height);
  out.image.assign(3 * pixels, 0);
  out.ids.assign(pixels, -1);
  out.depth.assign(pixels, kInfinity);
  const Vec3 light = config.light.normalized();
  // Ctrl-C: the thread that made the call polls between its bands, the others then skip theirs.
  std::atomic<bool> stop{false};
#pragma omp parallel for schedule(dynamic, 1)
  for (Index k = 0; k < bands; ++k) {
    if (stop.load(std::memory_order_relaxed)) continue;
    if (omp_get_thread_num() == 0 && interrupt.requested()) {
      stop = true;
      continue;
    }
    const Index row0 = k * kBandRows, row1 = std::min(height, row0 + kBandRows);
    // The pixel-centre rays of the band, made once and shared by every primitive.
    std::vector<Ray> rays(static_cast<size_t>((row1 - row0) * width));
    for (Index row = row0; row < row1; ++row)
      for (Index col = 0; col < width; ++col)
        rays[static_cast<size_t>((row - row0) * width + col)] = frame.ray(row, col, 0.5, 0.5);
    auto test = [&](Index id, Index row, Index col) {
      const size_t px = static_cast<size_t>(row * width + col);
      const Scalar t = scene.intersect_primitive(id, rays[static_cast<size_t>((row - row0) * width + col)],
                                                 t_min, out.depth[px]);
      if (t < out.depth[px]) {
        out.depth[px] = t;
        out.ids[px] = id;
      }
    };
    // Planes first: every pixel of the band.
    for (Index id = bounded; id < scene.primitive_count(); ++id)
      for (Index row = row0; row < row1; ++row)
        for (Index col = 0; col < width; ++col) test(id, row, col);
    for (Index m = start[static_cast<size_t>(k)]; m < start[static_cast<size_t>(k + 1)]; ++m) {
      const Index id = members[static_cast<size_t>(m)];
      const PixelBox& b = boxes[static_cast<size_t>(id)];
      const Scalar near_id = near[static_cast<size_t>(id)];
      for (Index row = std::max(row0, b.row0); row < std::min(row1, b.row1); ++row)
        for (Index col = b.col0; col < b.col1; ++col)
          if (out.depth[static_cast<size_t>(row * width + col)] > near_id) test(id, row, col);
    }
    for (Index row = row0; row < row1; ++row)
      for (Index col = 0; col < width; ++col) {
        const size_t px = static_cast<size_t>(row * width + col);
        const Ray& ray = rays[static_cast<size_t>((row - row0) * width + col)];
        Color c;
        if (out.ids[px] < 0) {
          c = sky.radiance(ray.direction);
        } else {
          Hit hit;
          hit.t = out.depth[px];
          hit.primitive = out.ids[px];
          scene.finish_hit(ray, hit);
          const Material& mat = scene.material(hit.material);
          const Vec3 to_eye = -ray.direction;
          const Scalar lambert = std::max(Scalar(0), hit.normal.dot(light));
          Scalar visible = 1;
          if (config.shadow_samples > 0 && lambert > 0)
            visible = light_visibility(scene, ray.origin + hit.t * ray.direction, light, config.light_radius,
                                       config.shadow_samples, t_min, static_cast<std::uint64_t>(px));
          const Vec3 half = (light + to_eye).normalized();
          const Scalar spec = config.specular > 0 && lambert > 0
                                  ? config.specular * std::pow(std::max(Scalar(0), hit.normal.dot(half)), config.shininess)
                                  : 0;
          if (mat.kind == MaterialKind::dielectric) {
            // Water: its body colour, lit, mixed with the sky it mirrors by Schlick's Fresnel factor.
            const Scalar cos_i = std::min(Scalar(1), std::abs(to_eye.dot(hit.normal)));
            const Scalar fresnel = schlick(cos_i, cos_i, 1, mat.ior);
            const Color body = Color(0.12, 0.38, 0.62) * (config.ambient + (1 - config.ambient) * visible * lambert);
            c = (1 - fresnel) * body + fresnel * sky.radiance(reflect(ray.direction, hit.normal)) +
                Color::Constant(visible * spec) + mat.emission;
          } else {
            c = mat.albedo * (config.ambient + (1 - config.ambient) * visible * lambert) +
                Color::Constant(visible * spec) + mat.emission;
          }
        }
        for (int ch = 0; ch < 3; ++ch) out.image[3 * px + static_cast<size_t>(ch)] = c[ch];
      }
  }
  interrupt.check();
  return out;
}

}  // namespace kinema::render
