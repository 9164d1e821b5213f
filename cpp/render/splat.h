// Spheres for a live view: per pixel the distance to the first sphere along the pixel-centre ray,
// the sphere's world-space normal there (float32) and its index (int32), which is what an
// OpenGL viewer composites by depth and shades (Polyscope's render-image quantities), colouring
// each pixel by its sphere's index. The same projection, binning and ray/sphere test as render::preview, without its
// shading or BVH: the cost is the pixels the spheres cover plus one pass over the image, so 1e5
// particles on a 1024 x 768 view take milliseconds on two cores. Deterministic for any thread
// count (bands of rows, spheres in index order within a band; ties keep the lower index).
#pragma once

#include <cstdint>
#include <vector>

#include "core/interrupt.h"
#include "render/config.h"

namespace kinema::render {

struct SplatResult {
  std::vector<float> depth;   // (height, width): distance along the pixel-centre ray, inf on a miss
  std::vector<float> normal;  // (height, width, 3): unit outward normal, 0 on a miss
  std::vector<std::int32_t> ids;  // (height, width): the hit sphere's index, -1 on a miss
  Index hits = 0;             // pixels that show a sphere
};

// centers: n rows of 3 (n < 2^31); radii: n values, or one shared by all when radius_count == 1.
// Radii must be > 0 and finite, centres finite (checked by the caller).
SplatResult splat_spheres(const Scalar* centers, Index n, const Scalar* radii, Index radius_count,
                          const Camera& camera, Interrupt& interrupt);

}  // namespace kinema::render
