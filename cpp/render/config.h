// Parameters of a path-traced render and of a preview: the camera (a pinhole), the sky that
// lights the scene, and the sampling options. Plain structs with defaults; units are those of
// the scene (lengths) and of radiance (any linear unit: the image is in the sky's units).
#pragma once

#include <cstdint>
#include <string>

#include "render/kernels.h"

namespace kinema::render {

// Pinhole camera at look_from looking at look_at; vfov is the full vertical field of view.
// Pixel (row, col) spans [col, col + 1) x [row, row + 1) with row 0 at the top of the image.
struct Camera {
  Vec3 look_from = Vec3(0, 0, 1);
  Vec3 look_at = Vec3(0, 0, 0);
  Vec3 up = Vec3(0, 1, 0);
  Scalar vfov_degrees = 40;
  Index width = 640;
  Index height = 480;
};

// Radiance of rays that leave the scene: L(d) = bottom + (top - bottom) (1 + d_y) / 2 for the
// unit direction d (uniform when top == bottom; Shirley's gradient sky).
struct Sky {
  Color bottom = Color::Ones();
  Color top = Color::Ones();
  Color radiance(const Vec3& d) const { return bottom + (top - bottom) * (0.5 * (1 + d.y())); }
};

struct RenderConfig {
  Index samples_per_pixel = 64;  // jittered sub-pixel samples (anti-aliasing)
  int max_depth = 16;            // bounces after which a path is cut (contributes nothing more)
  // Russian roulette starts at this bounce; a value >= max_depth switches it off.
  int roulette_depth = 3;
  std::uint64_t seed = 0;
  bool variance = false;  // also estimate the variance of each pixel's mean
};

// Blinn-Phong shading (Blinn 1977) under a distant light of angular radius light_radius:
//   colour = albedo (ambient + (1 - ambient) V max(0, n . l)) + specular V max(0, n . h)^shininess
// with h = (l + v) / |l + v| (v towards the eye) and V the light's visible fraction, estimated
// with shadow_samples rays to points of its disc (0: no shadows, V = 1).
struct PreviewConfig {
  Vec3 light = Vec3(0.3, 1, 0.5);  // direction towards a distant light (need not be unit)
  Scalar ambient = 0.25;
  Scalar specular = 0;              // Blinn-Phong's k_s (0: Lambert alone)
  Scalar shininess = 32;            // Blinn-Phong's exponent (> 0)
  Index shadow_samples = 0;         // rays per pixel towards the light (0: no shadows)
  Scalar light_radius = 0.05;       // angular radius of the light [rad]: soft shadows' penumbra
};

// Checks a camera (finite, look_from != look_at, up not along the view, 0 < vfov < 180,
// width and height >= 1) and throws InvalidArgument naming the field.
void validate(const Camera& camera);
void validate(const RenderConfig& config);

}  // namespace kinema::render
