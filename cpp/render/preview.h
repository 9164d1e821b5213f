// A fast preview for the frames of long simulations: a z-buffered splatter of the spheres and a
// rasteriser of the triangles, shaded by a distant light (Blinn-Phong, config.h),
//   colour = albedo (ambient + (1 - ambient) V max(0, n . l)) + specular V max(0, n . h)^shininess + emission,
// with soft shadows V from rays towards the light's disc (through the BVH: prepare() the scene
// first when shadow_samples > 0), glass drawn as water (a blue-green body colour mixed with the
// sky it reflects by Schlick's Fresnel factor), and the sky where nothing is hit. Each primitive is projected to the pixel box of its image
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
