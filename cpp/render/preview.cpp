// The z-buffered splatter/rasteriser behind render::preview.
#include "render/preview.h"

#include <algorithm>
#include <cmath>

#include "core/errors.h"
#include "render/camera.h"

namespace kinema::render {

namespace {

constexpr Index kBandRows = 8;

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
  // Pixel box covering the camera-space points (x, y) / z over the given x, y and z ranges
  // (z_lo > 0): x / z is monotone in x and in z there, so the corners bound it.
  PixelBox box(Scalar x_lo, Scalar x_hi, Scalar y_lo, Scalar y_hi, Scalar z_lo, Scalar z_hi) const {
    const Scalar sx[4] = {x_lo / z_lo, x_lo / z_hi, x_hi / z_lo, x_hi / z_hi};
    const Scalar sy[4] = {y_lo / z_lo, y_lo / z_hi, y_hi / z_lo, y_hi / z_hi};
    const Scalar u_lo = *std::min_element(sx, sx + 4) / right_len_, u_hi = *std::max_element(sx, sx + 4) / right_len_;
    const Scalar v_lo = *std::min_element(sy, sy + 4) / up_len_, v_hi = *std::max_element(sy, sy + 4) / up_len_;
    const auto w = static_cast<Scalar>(frame_.width()), h = static_cast<Scalar>(frame_.height());
    // ndc u in [-1, 1] maps to col + 0.5 = (u + 1) w / 2; v to row + 0.5 = (1 - v) h / 2. One
    // pixel of margin absorbs the rounding of the projection.
    PixelBox b;
    b.col0 = clamp_index(std::floor((u_lo + 1) * 0.5 * w - 0.5) - 1, frame_.width());
    b.col1 = clamp_index(std::ceil((u_hi + 1) * 0.5 * w - 0.5) + 2, frame_.width());
    b.row0 = clamp_index(std::floor((1 - v_hi) * 0.5 * h - 0.5) - 1, frame_.height());
    b.row1 = clamp_index(std::ceil((1 - v_lo) * 0.5 * h - 0.5) + 2, frame_.height());
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

// Near limit of the projection: primitives reaching closer than this (or behind the camera)
// get the whole image as their box instead.
constexpr Scalar kNearFraction = 1e-9;

PixelBox sphere_box(const Projector& p, const Scene::Sphere& s, Scalar scale) {
  const Vec3 c = p.to_camera(s.center);
  const Scalar r = s.radius;
  if (c.z() + r <= 0) return PixelBox{};
  if (c.z() - r <= kNearFraction * scale) return p.whole();
  return p.box(c.x() - r, c.x() + r, c.y() - r, c.y() + r, c.z() - r, c.z() + r);
}

PixelBox triangle_box(const Projector& p, const Scene::Triangle& t, Scalar scale) {
  const Vec3 a = p.to_camera(t.v0), b = p.to_camera(t.v0 + t.e1), c = p.to_camera(t.v0 + t.e2);
  const Vec3 lo = a.cwiseMin(b).cwiseMin(c), hi = a.cwiseMax(b).cwiseMax(c);
  if (hi.z() <= 0) return PixelBox{};
  if (lo.z() <= kNearFraction * scale) return p.whole();
  return p.box(lo.x(), hi.x(), lo.y(), hi.y(), lo.z(), hi.z());
}

}  // namespace

PreviewResult preview(const Scene& scene, const Camera& camera, const Sky& sky,
                      const PreviewConfig& config, Interrupt& interrupt) {
  validate(camera);
  if (!config.light.allFinite() || config.light.norm() == 0)
    throw InvalidArgument("light: expected a finite non-zero direction");
  if (!(config.ambient >= 0 && config.ambient <= 1))
    throw InvalidArgument("ambient: expected a number in [0, 1], got " + format_real(config.ambient));
  const CameraFrame frame(camera);
  const Projector projector(frame);
  const Index width = camera.width, height = camera.height;
  const Index s_count = scene.sphere_count(), bounded = s_count + scene.triangle_count();
  const Scalar scale = scene.scale(), t_min = kRayEpsilon * scale;

  // Pixel boxes of all bounded primitives, then a counting sort of the primitives into bands.
  std::vector<PixelBox> boxes(static_cast<size_t>(bounded));
#pragma omp parallel for schedule(static)
  for (Index i = 0; i < bounded; ++i)
    boxes[static_cast<size_t>(i)] =
        i < s_count ? sphere_box(projector, scene.spheres()[static_cast<size_t>(i)], scale)
                    : triangle_box(projector, scene.triangles()[static_cast<size_t>(i - s_count)], scale);
  const Index bands = (height + kBandRows - 1) / kBandRows;
  std::vector<Index> start(static_cast<size_t>(bands + 1), 0);
  for (const PixelBox& b : boxes)
    if (b.row0 < b.row1 && b.col0 < b.col1)
      for (Index k = b.row0 / kBandRows; k <= (b.row1 - 1) / kBandRows; ++k) ++start[static_cast<size_t>(k + 1)];
  for (Index k = 0; k < bands; ++k) start[static_cast<size_t>(k + 1)] += start[static_cast<size_t>(k)];
  std::vector<Index> members(static_cast<size_t>(start.back()));
  {
    std::vector<Index> fill(start.begin(), start.end() - 1);
    for (Index i = 0; i < bounded; ++i) {
      const PixelBox& b = boxes[static_cast<size_t>(i)];
      if (b.row0 < b.row1 && b.col0 < b.col1)
        for (Index k = b.row0 / kBandRows; k <= (b.row1 - 1) / kBandRows; ++k)
          members[static_cast<size_t>(fill[static_cast<size_t>(k)]++)] = i;
    }
  }
  interrupt.check();

  PreviewResult out;
  const auto pixels = static_cast<size_t>(width * height);
  out.image.assign(3 * pixels, 0);
  out.ids.assign(pixels, -1);
  out.depth.assign(pixels, kInfinity);
  const Vec3 light = config.light.normalized();
#pragma omp parallel for schedule(dynamic, 1)
  for (Index k = 0; k < bands; ++k) {
    const Index row0 = k * kBandRows, row1 = std::min(height, row0 + kBandRows);
    // Planes first: every pixel of the band.
    for (Index id = bounded; id < scene.primitive_count(); ++id)
      for (Index row = row0; row < row1; ++row)
        for (Index col = 0; col < width; ++col) {
          const size_t px = static_cast<size_t>(row * width + col);
          const Scalar t = scene.intersect_primitive(id, frame.ray(row, col, 0.5, 0.5), t_min, out.depth[px]);
          if (t < out.depth[px]) {
            out.depth[px] = t;
            out.ids[px] = id;
          }
        }
    for (Index m = start[static_cast<size_t>(k)]; m < start[static_cast<size_t>(k + 1)]; ++m) {
      const Index id = members[static_cast<size_t>(m)];
      const PixelBox& b = boxes[static_cast<size_t>(id)];
      for (Index row = std::max(row0, b.row0); row < std::min(row1, b.row1); ++row)
        for (Index col = b.col0; col < b.col1; ++col) {
          const size_t px = static_cast<size_t>(row * width + col);
          const Scalar t = scene.intersect_primitive(id, frame.ray(row, col, 0.5, 0.5), t_min, out.depth[px]);
          if (t < out.depth[px]) {
            out.depth[px] = t;
            out.ids[px] = id;
          }
        }
    }
    for (Index row = row0; row < row1; ++row)
      for (Index col = 0; col < width; ++col) {
        const size_t px = static_cast<size_t>(row * width + col);
        const Ray ray = frame.ray(row, col, 0.5, 0.5);
        Color c;
        if (out.ids[px] < 0) {
          c = sky.radiance(ray.direction);
        } else {
          Hit hit;
          hit.t = out.depth[px];
          hit.primitive = out.ids[px];
          scene.finish_hit(ray, hit);
          const Material& mat = scene.material(hit.material);
          const Color albedo = mat.kind == MaterialKind::dielectric ? Color::Constant(0.9) : mat.albedo;
          const Scalar lambert = std::max(Scalar(0), hit.normal.dot(light));
          c = albedo * (config.ambient + (1 - config.ambient) * lambert) + mat.emission;
        }
        for (int ch = 0; ch < 3; ++ch) out.image[3 * px + static_cast<size_t>(ch)] = c[ch];
      }
  }
  interrupt.check();
  return out;
}

}  // namespace kinema::render
