// Primary rays of the pinhole camera: d = normalize(-w + (2x - 1) a h u + (1 - 2y) h v) for
// image coordinates (x, y) in [0, 1)^2, h = tan(vfov / 2), a = width / height, (u, v, w) the
// camera frame with w pointing backwards (Shirley, "Ray Tracing in One Weekend", sec. 11).
#pragma once

#include "render/config.h"

namespace kinema::render {

class CameraFrame {
 public:
  explicit CameraFrame(const Camera& c) : origin_(c.look_from), width_(c.width), height_(c.height) {
    const Vec3 w = (c.look_from - c.look_at).normalized();
    const Vec3 u = c.up.cross(w).normalized();
    const Vec3 v = w.cross(u);
    const Scalar h = std::tan(0.5 * c.vfov_degrees * kPi / 180);
    const Scalar aspect = static_cast<Scalar>(c.width) / static_cast<Scalar>(c.height);
    forward_ = -w;
    right_ = aspect * h * u;
    up_ = h * v;
  }

  // The ray through image point (col + sx, row + sy) with sx, sy in [0, 1).
  Ray ray(Index row, Index col, Scalar sx, Scalar sy) const {
    const Scalar x = (static_cast<Scalar>(col) + sx) / static_cast<Scalar>(width_);
    const Scalar y = (static_cast<Scalar>(row) + sy) / static_cast<Scalar>(height_);
    return Ray{origin_, (forward_ + (2 * x - 1) * right_ + (1 - 2 * y) * up_).normalized()};
  }

  const Vec3& origin() const { return origin_; }
  const Vec3& forward() const { return forward_; }
  const Vec3& right() const { return right_; }
  const Vec3& up() const { return up_; }
  Index width() const { return width_; }
  Index height() const { return height_; }

 private:
  Vec3 origin_, forward_, right_, up_;
  Index width_, height_;
};

}  // namespace kinema::render
