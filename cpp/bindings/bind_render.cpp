// kinema._core.render: the path tracer and the preview behind km.render. Arrays arrive checked
// and C-contiguous from python/kinema/render.py; images are handed over without a copy.
#include <array>
#include <string>

#include "bindings/common.h"
#include "render/preview.h"
#include "render/splat.h"
#include "render/tracer.h"

namespace kinema::bind {

namespace {

using render::Color;
using render::Vec3;
using Triple = std::array<Scalar, 3>;

Vec3 vec(const Triple& t) { return Vec3(t[0], t[1], t[2]); }
Color color(const Triple& t) { return Color(t[0], t[1], t[2]); }

render::Camera camera(const Triple& look_from, const Triple& look_at, const Triple& up, Scalar vfov,
                      Index width, Index height) {
  render::Camera c;
  c.look_from = vec(look_from);
  c.look_at = vec(look_at);
  c.up = vec(up);
  c.vfov_degrees = vfov;
  c.width = width;
  c.height = height;
  render::validate(c);
  return c;
}

render::Sky sky(const Triple& bottom, const Triple& top) {
  render::Sky s;
  s.bottom = color(bottom);
  s.top = color(top);
  return s;
}

// Rows of an (n, 3) float64 array, or a ValueError naming it.
Index rows3(py::array& a, const char* name) {
  if (a.ndim() != 2 || a.shape(1) != 3)
    throw InvalidArgument(std::string(name) + ": expected shape (n, 3)");
  return a.shape(0);
}

}  // namespace

void bind_render(py::module_& m) {
  m.def(
      "splat_spheres",
      [](py::array centers, py::array radii, const Triple& look_from, const Triple& look_at,
         const Triple& up, Scalar vfov, Index width, Index height) {
        const render::Camera cam = camera(look_from, look_at, up, vfov, width, height);
        const Index n = rows3(centers, "centers");
        const Index radius_count = radii.size() == 1 ? 1 : n;
        const Scalar* c = checked_data(centers, "centers", 3 * n, false);
        const Scalar* r = checked_data(radii, "radii", radius_count, false);
        render::SplatResult out;
        {
          Interrupt interrupt = python_interrupt();
          ReleaseGil release;
          out = render::splat_spheres(c, n, r, radius_count, cam, interrupt);
        }
        return py::make_tuple(to_numpy(std::move(out.depth), {height, width}),
                              to_numpy(std::move(out.normal), {height, width, 3}),
                              to_numpy(std::move(out.ids), {height, width}), out.hits);
      },
      py::arg("centers"), py::arg("radii"), py::arg("look_from"), py::arg("look_at"),
      py::arg("up"), py::arg("vfov"), py::arg("width"), py::arg("height"));
  py::class_<render::Scene>(m, "Scene")
      .def(py::init<>())
      .def(
          "add_material",
          [](render::Scene& s, const std::string& kind, const Triple& albedo, Scalar fuzz, Scalar ior,
             const Triple& emission, const Triple& absorption) {
            render::Material mat;
            if (kind == "lambertian") {
              mat.kind = render::MaterialKind::lambertian;
            } else if (kind == "metal") {
              mat.kind = render::MaterialKind::metal;
            } else if (kind == "dielectric") {
              mat.kind = render::MaterialKind::dielectric;
            } else {
              throw InvalidArgument("kind: expected lambertian, metal or dielectric, got " + kind);
            }
            mat.albedo = color(albedo);
            mat.fuzz = fuzz;
            mat.ior = ior;
            mat.emission = color(emission);
            mat.absorption = color(absorption);
            return s.add_material(mat);
          },
          py::arg("kind"), py::arg("albedo"), py::arg("fuzz"), py::arg("ior"), py::arg("emission"),
          py::arg("absorption") = Triple{0, 0, 0})
      .def(
          "add_spheres",
          [](render::Scene& s, py::array centers, py::array radii, Index material) {
            const Index n = rows3(centers, "centers");
            s.add_spheres(checked_data(centers, "centers", 3 * n, false),
                          checked_data(radii, "radii", n, false), n, material);
          },
          py::arg("centers"), py::arg("radii"), py::arg("material"))
      .def(
          "add_mesh",
          [](render::Scene& s, py::array vertices, IndexArray triangles, Index material) {
            const Index m = rows3(vertices, "vertices");
            if (triangles.ndim() != 2 || triangles.shape(1) != 3)
              throw InvalidArgument("triangles: expected shape (k, 3)");
            s.add_mesh(checked_data(vertices, "vertices", 3 * m, false), m, triangles.data(),
                       triangles.shape(0), material);
          },
          py::arg("vertices"), py::arg("triangles"), py::arg("material"))
      .def(
          "add_plane",
          [](render::Scene& s, const Triple& point, const Triple& normal, Index material) {
            s.add_plane(vec(point), vec(normal), material);
          },
          py::arg("point"), py::arg("normal"), py::arg("material"))
      .def_property_readonly("sphere_count", &render::Scene::sphere_count)
      .def_property_readonly("triangle_count", &render::Scene::triangle_count)
      .def_property_readonly("plane_count", &render::Scene::plane_count)
      .def(
          "render",
          [](render::Scene& s, const Triple& look_from, const Triple& look_at, const Triple& up,
             Scalar vfov, Index width, Index height, const Triple& sky_bottom, const Triple& sky_top,
             Index spp, int max_depth, int roulette_depth, std::uint64_t seed, bool variance) {
            const render::Camera cam = camera(look_from, look_at, up, vfov, width, height);
            render::RenderConfig config;
            config.samples_per_pixel = spp;
            config.max_depth = max_depth;
            config.roulette_depth = roulette_depth;
            config.seed = seed;
            config.variance = variance;
            render::RenderResult r;
            {
              Interrupt interrupt = python_interrupt();
              ReleaseGil release;
              r = render::render(s, cam, sky(sky_bottom, sky_top), config, interrupt);
            }
            py::dict stats;
            stats["rays"] = r.stats.rays;
            stats["seconds"] = r.stats.seconds;
            stats["bvh_seconds"] = r.stats.bvh_seconds;
            stats["bvh_nodes"] = r.stats.bvh_nodes;
            stats["bvh_depth"] = r.stats.bvh_depth;
            py::object var = py::none();
            if (variance) var = to_numpy(std::move(r.variance), {height, width, 3});
            return py::make_tuple(to_numpy(std::move(r.image), {height, width, 3}), var, stats);
          },
          py::arg("look_from"), py::arg("look_at"), py::arg("up"), py::arg("vfov"), py::arg("width"),
          py::arg("height"), py::arg("sky_bottom"), py::arg("sky_top"), py::arg("spp"),
          py::arg("max_depth"), py::arg("roulette_depth"), py::arg("seed"), py::arg("variance"))
      .def(
          "preview",
          [](render::Scene& s, const Triple& look_from, const Triple& look_at, const Triple& up,
             Scalar vfov, Index width, Index height, const Triple& sky_bottom, const Triple& sky_top,
             const Triple& light, Scalar ambient, Scalar specular, Scalar shininess, Index shadow_samples,
             Scalar light_radius) {
            const render::Camera cam = camera(look_from, look_at, up, vfov, width, height);
            render::PreviewConfig config;
            config.light = vec(light);
            config.ambient = ambient;
            config.specular = specular;
            config.shininess = shininess;
            config.shadow_samples = shadow_samples;
            config.light_radius = light_radius;
            render::PreviewResult r;
            {
              Interrupt interrupt = python_interrupt();
              ReleaseGil release;
              if (shadow_samples > 0) s.prepare();  // shadow rays go through the BVH
              r = render::preview(s, cam, sky(sky_bottom, sky_top), config, interrupt);
            }
            return py::make_tuple(to_numpy(std::move(r.image), {height, width, 3}),
                                  to_numpy(std::move(r.ids), {height, width}),
                                  to_numpy(std::move(r.depth), {height, width}));
          },
          py::arg("look_from"), py::arg("look_at"), py::arg("up"), py::arg("vfov"), py::arg("width"),
          py::arg("height"), py::arg("sky_bottom"), py::arg("sky_top"), py::arg("light"),
          py::arg("ambient"), py::arg("specular") = 0.0, py::arg("shininess") = 32.0,
          py::arg("shadow_samples") = 0, py::arg("light_radius") = 0.05)
      .def(
          "primary_hits",
          [](render::Scene& s, const Triple& look_from, const Triple& look_at, const Triple& up,
             Scalar vfov, Index width, Index height) {
            const render::Camera cam = camera(look_from, look_at, up, vfov, width, height);
            std::vector<Index> ids;
            {
              ReleaseGil release;
              ids = render::primary_hits(s, cam);
            }
            return to_numpy(std::move(ids), {height, width});
          },
          py::arg("look_from"), py::arg("look_at"), py::arg("up"), py::arg("vfov"), py::arg("width"),
          py::arg("height"))
      .def(
          "intersect",
          [](render::Scene& s, py::array origins, py::array directions, bool brute_force) {
            const Index n = rows3(origins, "origins");
            const Scalar* o = checked_data(origins, "origins", 3 * n, false);
            const Scalar* d = checked_data(directions, "directions", 3 * n, false);
            std::vector<Scalar> t(static_cast<size_t>(n));
            std::vector<Index> ids(static_cast<size_t>(n));
            {
              ReleaseGil release;
              s.prepare();
#pragma omp parallel for schedule(static)
              for (Index i = 0; i < n; ++i) {
                const render::Ray ray{Vec3(o[3 * i], o[3 * i + 1], o[3 * i + 2]),
                                      Vec3(d[3 * i], d[3 * i + 1], d[3 * i + 2])};
                const render::Hit h = brute_force ? s.intersect_brute_force(ray, 0, render::kInfinity)
                                                  : s.intersect(ray, 0, render::kInfinity);
                t[static_cast<size_t>(i)] = h.t;
                ids[static_cast<size_t>(i)] = h.primitive;
              }
            }
            return py::make_tuple(to_numpy(std::move(t), {n}), to_numpy(std::move(ids), {n}));
          },
          py::arg("origins"), py::arg("directions"), py::arg("brute_force"));
}

}  // namespace kinema::bind
