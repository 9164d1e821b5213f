// A fast preview for the frames of long simulations: a z-buffered splatter of the spheres and a
// rasteriser of the triangles, shaded by a distant light (Lambert's cosine law),
//   colour = albedo (ambient + (1 - ambient) max(0, n . l)) + emission,
// and the sky where nothing is hit. Each primitive is projected to the pixel box of its image
// (tangent cones for spheres, projected vertices for triangles), and the pixel centres inside
// are tested with the same ray/primitive intersection as the path tracer, so the preview's
// visible primitive equals the tracer's primary hit at every pixel centre. OpenMP over bands
// of rows; primitives are binned to bands first and visited in a fixed order within each band,
// so the image does not depend on the thread count.
#pragma once

#include <vector>

#include "core/interrupt.h"
#include "render/config.h"
#include "render/scene.h"

namespace kinema::render {

struct PreviewResult {
  std::vector<Scalar> image;  // (height, width, 3)
  std::vector<Index> ids;     // (height, width): visible primitive or -1
  std::vector<Scalar> depth;  // (height, width): distance along the centre ray, inf on a miss
};

PreviewResult preview(const Scene& scene, const Camera& camera, const Sky& sky,
                      const PreviewConfig& config, Interrupt& interrupt);

}  // namespace kinema::render
