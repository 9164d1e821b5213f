// The sphere splatter behind render::splat_spheres.
#include "render/splat.h"

#include <omp.h>

#include <atomic>
#include <cmath>
#include <limits>

#include "core/errors.h"
#include "render/projection.h"

namespace kinema::render {

SplatResult splat_spheres(const Scalar* centers, Index n, const Scalar* radii, Index radius_count,
                          const Camera& camera, Interrupt& interrupt) {
  validate(camera);
  if (n > static_cast<Index>(INT32_MAX)) throw InvalidArgument("centers: at most 2^31 - 1 spheres");
  const CameraFrame frame(camera);
  const detail::Projector projector(frame);
  const Index width = camera.width, height = camera.height;
  auto center = [&](Index i) { return Vec3(centers[3 * i], centers[3 * i + 1], centers[3 * i + 2]); };
  auto radius = [&](Index i) { return radii[radius_count == 1 ? 0 : i]; };

  // Boxes, and the nearest distance any hit of sphere i can have (a pixel already holding a
  // nearer hit skips it), shrunk by far more than its rounding.
  std::vector<detail::PixelBox> boxes(static_cast<size_t>(n));
  std::vector<Scalar> near(static_cast<size_t>(n));
#pragma omp parallel for schedule(static)
  for (Index i = 0; i < n; ++i) {
    boxes[static_cast<size_t>(i)] = detail::sphere_box(projector, center(i), radius(i));
    near[static_cast<size_t>(i)] = ((center(i) - frame.origin()).norm() - radius(i)) * (1 - 1e-9);
  }
  std::vector<Index> start, members;
  detail::bin_to_bands(boxes, height, start, members);
  interrupt.check();

  SplatResult out;
  const auto pixels = static_cast<size_t>(width * height);
  out.depth.assign(pixels, std::numeric_limits<float>::infinity());
  out.normal.assign(3 * pixels, 0.0f);
  out.ids.assign(pixels, -1);
  const Index bands = static_cast<Index>(start.size()) - 1;
  std::atomic<bool> stop{false};
  Index hits = 0;
#pragma omp parallel reduction(+ : hits)
  {
    std::vector<Vec3> dirs;
    std::vector<Scalar> depth;
    std::vector<Index> ids;
#pragma omp for schedule(dynamic, 1)
    for (Index k = 0; k < bands; ++k) {
      if (stop.load(std::memory_order_relaxed)) continue;
      if (omp_get_thread_num() == 0 && interrupt.requested()) {
        stop = true;
        continue;
      }
      const Index row0 = k * detail::kBandRows, row1 = std::min(height, row0 + detail::kBandRows);
      const auto band = static_cast<size_t>((row1 - row0) * width);
      dirs.resize(band);
      depth.assign(band, kInfinity);
      ids.assign(band, -1);
      for (Index row = row0; row < row1; ++row)
        for (Index col = 0; col < width; ++col)
          dirs[static_cast<size_t>((row - row0) * width + col)] = frame.ray(row, col, 0.5, 0.5).direction;
      const Vec3& eye = frame.origin();
      for (Index m = start[static_cast<size_t>(k)]; m < start[static_cast<size_t>(k + 1)]; ++m) {
        const Index id = members[static_cast<size_t>(m)];
        const detail::PixelBox& b = boxes[static_cast<size_t>(id)];
        const Vec3 oc = eye - center(id);
        const Scalar r = radius(id), c = oc.squaredNorm() - r * r, near_id = near[static_cast<size_t>(id)];
        for (Index row = std::max(row0, b.row0); row < std::min(row1, b.row1); ++row)
          for (Index col = b.col0; col < b.col1; ++col) {
            const size_t px = static_cast<size_t>((row - row0) * width + col);
            if (!(depth[px] > near_id)) continue;
            // |oc + t d|^2 = r^2 with |d| = 1: t = -b - sqrt(b^2 - c), the near root.
            const Scalar bb = oc.dot(dirs[px]), disc = bb * bb - c;
            if (disc < 0) continue;
            const Scalar t = -bb - std::sqrt(disc);
            if (t > 0 && t < depth[px]) {
              depth[px] = t;
              ids[px] = id;
            }
          }
      }
      for (size_t px = 0; px < band; ++px) {
        const Index id = ids[px];
        if (id < 0) continue;
        ++hits;
        const size_t out_px = static_cast<size_t>(row0 * width) + px;
        const Vec3 normal = (eye + depth[px] * dirs[px] - center(id)) / radius(id);
        out.depth[out_px] = static_cast<float>(depth[px]);
        for (int a = 0; a < 3; ++a) out.normal[3 * out_px + static_cast<size_t>(a)] = static_cast<float>(normal[a]);
        out.ids[out_px] = static_cast<std::int32_t>(id);
      }
    }
  }
  interrupt.check();
  out.hits = hits;
  return out;
}

}  // namespace kinema::render
