// Projection of primitives to the pixels whose centre rays may hit them, shared by the preview
// (render::preview) and the sphere splatter (render::splat_spheres): the pixel box of a sphere from
// its tangent cones, in the pinhole camera of camera.h. Images are processed in bands of kBandRows
// rows; each primitive is binned to the bands its box meets.
#pragma once

#include <algorithm>
#include <cmath>
#include <vector>

#include "render/camera.h"

namespace kinema::render::detail {

inline constexpr Index kBandRows = 8;

// Pixel box [row0, row1) x [col0, col1) of a primitive, empty when row0 >= row1.
struct PixelBox {
  Index row0 = 0, row1 = 0, col0 = 0, col1 = 0;
};

// Projects camera-space points (x, y, z), z > 0 along the view, to continuous pixel coordinates.
class Projector {
 public:
  explicit Projector(const CameraFrame& f)
      : frame_(f),
        right_unit_(f.right().normalized()),
        up_unit_(f.up().normalized()),
        right_len_(f.right().norm()),
        up_len_(f.up().norm()) {}

  Vec3 to_camera(const Vec3& p) const {
    const Vec3 q = p - frame_.origin();
    return Vec3(q.dot(right_unit_), q.dot(up_unit_), q.dot(frame_.forward()));
  }
  // The pixels whose centres lie in the image-plane rectangle x / z in [sx_lo, sx_hi],
  // y / z in [sy_lo, sy_hi]: ndc u = (x / z) / |right| maps to col + 0.5 = (u + 1) w / 2, and
  // v = (y / z) / |up| to row + 0.5 = (1 - v) h / 2. A millionth of a pixel absorbs rounding.
  PixelBox box(Scalar sx_lo, Scalar sx_hi, Scalar sy_lo, Scalar sy_hi) const {
    const auto w = static_cast<Scalar>(frame_.width()), h = static_cast<Scalar>(frame_.height());
    constexpr Scalar slack = 1e-6;
    PixelBox b;
    b.col0 = clamp_index(std::ceil((sx_lo / right_len_ + 1) * 0.5 * w - 0.5 - slack), frame_.width());
    b.col1 = clamp_index(std::floor((sx_hi / right_len_ + 1) * 0.5 * w - 0.5 + slack) + 1, frame_.width());
    b.row0 = clamp_index(std::ceil((1 - sy_hi / up_len_) * 0.5 * h - 0.5 - slack), frame_.height());
    b.row1 = clamp_index(std::floor((1 - sy_lo / up_len_) * 0.5 * h - 0.5 + slack) + 1, frame_.height());
    return b;
  }
  PixelBox whole() const { return PixelBox{0, frame_.height(), 0, frame_.width()}; }

 private:
  static Index clamp_index(Scalar v, Index n) {
    if (!(v > 0)) return 0;  // NaN too
    return v >= static_cast<Scalar>(n) ? n : static_cast<Index>(v);
  }
  const CameraFrame& frame_;
  Vec3 right_unit_, up_unit_;
  Scalar right_len_, up_len_;
};

// Range of a / z over a sphere of radius r centred at (a, z) in a plane through the eye: the
// tangent lines from the eye make angles theta +- h with the view axis, tan(theta) = a / z,
// tan(h) = r / sqrt(a^2 + z^2 - r^2), combined by the tangent addition formula. False when the
// sphere reaches within 1e-6 of the eye or a tangent line is 90 degrees or more off the axis.
inline bool tangent_range(Scalar a, Scalar z, Scalar r, Scalar& lo, Scalar& hi) {
  const Scalar d2 = a * a + z * z;
  if (z <= 0 || d2 <= r * r * (1 + 2e-6)) return false;
  const Scalar t = a / z, th = r / std::sqrt(d2 - r * r);
  const Scalar den_hi = 1 - t * th, den_lo = 1 + t * th;
  if (den_hi <= 1e-6 || den_lo <= 1e-6) return false;
  // A relative widening of 1e-12 covers the rounding of these few operations.
  const Scalar pad = 1e-12 * (1 + std::abs(t) + th) / std::min(den_hi, den_lo);
  lo = (t - th) / den_lo - pad;
  hi = (t + th) / den_hi + pad;
  return true;
}

// The pixel box of a sphere (centre c, radius r): empty behind the eye, the whole image when it
// reaches the eye plane.
inline PixelBox sphere_box(const Projector& p, const Vec3& center, Scalar radius) {
  const Vec3 c = p.to_camera(center);
  if (c.z() + radius <= 0) return PixelBox{};
  Scalar x_lo, x_hi, y_lo, y_hi;
  if (!tangent_range(c.x(), c.z(), radius, x_lo, x_hi) || !tangent_range(c.y(), c.z(), radius, y_lo, y_hi))
    return p.whole();
  return p.box(x_lo, x_hi, y_lo, y_hi);
}

// Counting sort of primitives into bands of kBandRows rows: members[start[k] .. start[k + 1]) are
// the primitives whose boxes meet band k, in increasing index (so results do not depend on threads).
inline void bin_to_bands(const std::vector<PixelBox>& boxes, Index height, std::vector<Index>& start,
                         std::vector<Index>& members) {
  const Index bands = (height + kBandRows - 1) / kBandRows;
  start.assign(static_cast<size_t>(bands + 1), 0);
  for (const PixelBox& b : boxes)
    if (b.row0 < b.row1 && b.col0 < b.col1)
      for (Index k = b.row0 / kBandRows; k <= (b.row1 - 1) / kBandRows; ++k) ++start[static_cast<size_t>(k + 1)];
  for (Index k = 0; k < bands; ++k) start[static_cast<size_t>(k + 1)] += start[static_cast<size_t>(k)];
  members.resize(static_cast<size_t>(start.back()));
  std::vector<Index> fill(start.begin(), start.end() - 1);
  for (Index i = 0; i < static_cast<Index>(boxes.size()); ++i) {
    const PixelBox& b = boxes[static_cast<size_t>(i)];
    if (b.row0 < b.row1 && b.col0 < b.col1)
      for (Index k = b.row0 / kBandRows; k <= (b.row1 - 1) / kBandRows; ++k)
        members[static_cast<size_t>(fill[static_cast<size_t>(k)]++)] = i;
  }
}

}  // namespace kinema::render::detail
