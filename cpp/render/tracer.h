// The Monte Carlo path tracer: for every pixel, the mean over jittered sub-pixel samples of
//   L = sum_k beta_k L_e(x_k) + beta_K L_sky(d_K),  beta_{k+1} = beta_k f cos / (pdf q_k)
// along a path of BSDF-sampled bounces (Kajiya 1986), with Russian roulette survival q_k after
// `roulette_depth` bounces (PBRT 3rd ed., sec. 13.7). The materials' sampling makes
// f cos / pdf = albedo for all three (cosine-weighted Lambertian, Shirley's fuzzy metal,
// Fresnel-Schlick-chosen reflection or refraction for glass).
//
// Reproducibility: sample s of pixel p draws from its own PCG32 stream seeded from (seed, p, s)
// and a pixel sums its samples in order, so an image is bitwise identical for any thread count.
#pragma once

#include <vector>

#include "core/interrupt.h"
#include "render/config.h"
#include "render/scene.h"

namespace kinema::render {

struct RenderStats {
  Index rays = 0;        // closest-hit queries traced
  Scalar seconds = 0;    // wall time of the tracing (BVH build excluded)
  Scalar bvh_seconds = 0;
  Index bvh_nodes = 0;
  int bvh_depth = 0;
};

struct RenderResult {
  std::vector<Scalar> image;     // (height, width, 3) mean radiance per pixel
  std::vector<Scalar> variance;  // (height, width, 3) variance of that mean (config.variance)
  RenderStats stats;
};

// Radiance carried back along one path starting with `ray`; `rays` counts the queries.
Color trace_path(const Scene& scene, const Sky& sky, const RenderConfig& config, Ray ray, Rng& rng,
                 Index& rays);

// Renders the scene (building its BVH if needed). Checks `interrupt` between bands of rows.
RenderResult render(Scene& scene, const Camera& camera, const Sky& sky, const RenderConfig& config,
                    Interrupt& interrupt);

// The primitive id hit by the ray through each pixel's centre (-1 for none), (height, width).
std::vector<Index> primary_hits(Scene& scene, const Camera& camera);

// Rows handed to the thread team between two Ctrl-C checks.
Index band_rows(Index height);

}  // namespace kinema::render
