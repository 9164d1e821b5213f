// Path tracing loop and the parallel pixel loop (OpenMP, dynamic schedule over rows).
#include "render/tracer.h"

#include <omp.h>

#include <chrono>
#include <string>

#include "core/errors.h"
#include "core/parallel.h"
#include "render/camera.h"

namespace kinema::render {

void validate(const Camera& c) {
  if (!c.look_from.allFinite()) throw InvalidArgument("look_from: expected finite coordinates");
  if (!c.look_at.allFinite()) throw InvalidArgument("look_at: expected finite coordinates");
  if (!c.up.allFinite()) throw InvalidArgument("up: expected finite coordinates");
  const Vec3 view = c.look_at - c.look_from;
  if (view.norm() == 0) throw InvalidArgument("look_at: must differ from look_from");
  if (c.up.norm() == 0 || view.normalized().cross(c.up.normalized()).norm() < 1e-9)
    throw InvalidArgument("up: must not be zero or parallel to the viewing direction");
  if (!(c.vfov_degrees > 0 && c.vfov_degrees < 180))
    throw InvalidArgument("vfov: expected degrees in (0, 180), got " + format_real(c.vfov_degrees));
  if (c.width < 1 || c.height < 1)
    throw InvalidArgument("width, height: expected >= 1 pixels, got " + std::to_string(c.width) + " x " +
                          std::to_string(c.height));
}

void validate(const RenderConfig& c) {
  if (c.samples_per_pixel < 1)
    throw InvalidArgument("spp: expected >= 1 samples per pixel, got " + std::to_string(c.samples_per_pixel));
  if (c.variance && c.samples_per_pixel < 2)
    throw InvalidArgument("spp: a variance estimate needs >= 2 samples per pixel");
  if (c.max_depth < 1) throw InvalidArgument("max_depth: expected >= 1, got " + std::to_string(c.max_depth));
  if (c.roulette_depth < 1)
    throw InvalidArgument("roulette_depth: expected >= 1, got " + std::to_string(c.roulette_depth));
}

constexpr Index kSamplePass = 16;

Index band_rows(Index height) { return std::min<Index>(height, std::max(8, 4 * num_threads())); }

Color trace_path(const Scene& scene, const Sky& sky, const RenderConfig& config, Ray ray, Rng& rng,
                 Index& rays) {
  const Scalar t_min = kRayEpsilon * scene.scale();
  Color radiance = Color::Zero();
  Color beta = Color::Ones();
  for (int depth = 0; depth < config.max_depth; ++depth) {
    const Hit hit = scene.intersect(ray, t_min, kInfinity);
    ++rays;
    if (hit.primitive < 0) {
      radiance += beta * sky.radiance(ray.direction);
      break;
    }
    const Material& m = scene.material(hit.material);
    radiance += beta * m.emission;
    const Vec3& n = hit.normal;
    const Vec3& d = ray.direction;
    Vec3 next = Vec3::Zero();
    switch (m.kind) {
      case MaterialKind::lambertian: {  // f cos / pdf = (a / pi) cos / (cos / pi) = a
        const Scalar u1 = rng.uniform(), u2 = rng.uniform();
        next = cosine_hemisphere(n, u1, u2);
        beta *= m.albedo;
        break;
      }
      case MaterialKind::metal: {
        next = reflect(d, n);
        if (m.fuzz > 0) {
          const Scalar u1 = rng.uniform(), u2 = rng.uniform(), u3 = rng.uniform();
          next = (next + m.fuzz * uniform_ball(u1, u2, u3)).normalized();
        }
        if (next.dot(n) <= 0) return radiance;  // scattered into the surface: absorbed
        beta *= m.albedo;
        break;
      }
      case MaterialKind::dielectric: {  // choose R or T with their probabilities: weight 1
        // A back-face hit ends a segment inside the medium: Beer-Lambert over its length.
        if (!hit.front_face) beta *= (-m.absorption * hit.t).exp();
        const Scalar eta_i = hit.front_face ? 1 : m.ior, eta_t = hit.front_face ? m.ior : 1;
        const Scalar cos_i = std::min(Scalar(1), -d.dot(n));
        Vec3 transmitted;
        Scalar cos_t = 0;
        const bool refracts = refract(d, n, eta_i / eta_t, transmitted, cos_t);
        const Scalar r = refracts ? schlick(cos_i, cos_t, eta_i, eta_t) : 1;
        next = rng.uniform() < r ? reflect(d, n) : transmitted;
        break;
      }
    }
    if (beta.maxCoeff() <= 0) break;
    if (depth + 1 >= config.roulette_depth) {
      const Scalar q = roulette_survival(beta);
      if (rng.uniform() >= q) break;
      beta /= q;
    }
    ray = Ray{ray.origin + hit.t * d, next};
  }
  return radiance;
}

RenderResult render(Scene& scene, const Camera& camera, const Sky& sky, const RenderConfig& config,
                    Interrupt& interrupt) {
  validate(camera);
  validate(config);
  RenderResult result;
  result.stats.bvh_seconds = scene.prepare();
  result.stats.bvh_nodes = static_cast<Index>(scene.bvh().nodes().size());
  result.stats.bvh_depth = scene.bvh().depth();
  const CameraFrame frame(camera);
  const Index width = camera.width, height = camera.height, spp = config.samples_per_pixel;
  result.image.assign(static_cast<size_t>(3 * width * height), 0);
  // Welford's running mean (kept in the image) and sum of squared deviations, per channel. The
  // samples are taken in passes of kSamplePass so that Ctrl-C is honoured quickly even at high
  // spp; each pixel still adds its samples in the order 0, 1, ..., spp - 1.
  std::vector<Scalar> m2(result.image.size(), 0);
  std::vector<Index> row_rays(static_cast<size_t>(height), 0);
  const auto start = std::chrono::steady_clock::now();
  const Index band = band_rows(height);
  for (Index s0 = 0; s0 < spp; s0 += kSamplePass) {
    const Index s1 = std::min(spp, s0 + kSamplePass);
    for (Index row0 = 0; row0 < height; row0 += band) {
      interrupt.check();
      const Index row1 = std::min(height, row0 + band);
#pragma omp parallel for schedule(dynamic, 1)
      for (Index row = row0; row < row1; ++row) {
        Index rays = 0;
        for (Index col = 0; col < width; ++col) {
          const Index pixel = row * width + col;
          Scalar* mean_px = &result.image[static_cast<size_t>(3 * pixel)];
          Scalar* m2_px = &m2[static_cast<size_t>(3 * pixel)];
          Color mean(mean_px[0], mean_px[1], mean_px[2]), dev2(m2_px[0], m2_px[1], m2_px[2]);
          for (Index s = s0; s < s1; ++s) {
            Rng rng(config.seed, static_cast<std::uint64_t>(pixel), static_cast<std::uint64_t>(s));
            const Scalar sx = rng.uniform(), sy = rng.uniform();
            const Color l = trace_path(scene, sky, config, frame.ray(row, col, sx, sy), rng, rays);
            const Color delta = l - mean;
            mean += delta / static_cast<Scalar>(s + 1);
            dev2 += delta * (l - mean);
          }
          for (int c = 0; c < 3; ++c) {
            mean_px[c] = mean[c];
            m2_px[c] = dev2[c];
          }
        }
        row_rays[static_cast<size_t>(row)] += rays;
      }
    }
  }
  if (config.variance) {
    result.variance = std::move(m2);
    for (Scalar& v : result.variance) v /= static_cast<Scalar>((spp - 1) * spp);
  }
  interrupt.check();
  result.stats.seconds =
      std::chrono::duration<Scalar>(std::chrono::steady_clock::now() - start).count();
  for (Index r : row_rays) result.stats.rays += r;
  return result;
}

std::vector<Index> primary_hits(Scene& scene, const Camera& camera) {
  validate(camera);
  scene.prepare();
  const CameraFrame frame(camera);
  const Scalar t_min = kRayEpsilon * scene.scale();
  std::vector<Index> ids(static_cast<size_t>(camera.width * camera.height));
  parallel_for(camera.height, [&](Index row) {
    for (Index col = 0; col < camera.width; ++col)
      ids[static_cast<size_t>(row * camera.width + col)] =
          scene.intersect(frame.ray(row, col, 0.5, 0.5), t_min, kInfinity).primitive;
  });
  return ids;
}

}  // namespace kinema::render
