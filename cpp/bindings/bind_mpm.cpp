// kinema._core.mpm: the material point method behind km.mpm.Simulation.
// State arrays are zero-copy views whose owner is the C++ State itself (held by a shared
// pointer in the view's capsule): adding particles builds a new State, so a view taken before
// add_particles stays valid memory but is detached from the simulation.
#include <memory>
#include <optional>

#include "bindings/common.h"
#include "core/rollback.h"
#include "core/errors.h"
#include "mpm/kernels.h"
#include "mpm/solver.h"

namespace kinema::bind {

namespace {

struct PySimulation {
  PySimulation(std::vector<Index> shape, Scalar h, std::vector<Scalar> gravity, const std::string& boundary,
               std::vector<Scalar> origin, Scalar friction, Scalar max_cells_per_step, Scalar max_dt) {
    model = mpm::make_model(static_cast<int>(shape.size()), shape, h, origin,
                            mpm::parse_boundary(boundary, "boundary"), friction);
    if (gravity.size() != shape.size())
      throw InvalidArgument("gravity: expected " + std::to_string(shape.size()) + " components, got " +
                            std::to_string(gravity.size()));
    config.gravity = {0, 0, 0};
    std::copy(gravity.begin(), gravity.end(), config.gravity.begin());
    config.max_cells_per_step = max_cells_per_step;
    config.max_dt = max_dt;
    state = std::make_shared<mpm::State>(model.dim);
    solver = std::make_unique<mpm::Solver>(model, config);
  }

  int dim() const { return model.dim; }

  py::tuple add_particles(py::array positions, const std::string& material, Scalar density,
                          Scalar youngs_modulus, Scalar poisson_ratio, py::array velocity, py::array volume,
                          Scalar friction_angle, Scalar cohesion) {
    const int d = model.dim;
    if (positions.ndim() != 2 || positions.shape(1) != d)
      throw InvalidArgument("positions: expected shape (n, " + std::to_string(d) + ")");
    const Index m = positions.shape(0);
    const Scalar* x = checked_data(positions, "positions", m * d, false);
    const Scalar* v = checked_data(velocity, "velocity", m * d, false);
    const Scalar* vol = checked_data(volume, "volume", m, false);
    for (Index p = 0; p < m; ++p) {
      for (int a = 0; a < d; ++a) {
        const Scalar xa = x[p * d + a];
        if (!(xa >= model.origin[a] && xa <= model.upper(a)))
          throw InvalidArgument("positions: particle " + std::to_string(p) + " lies outside the domain [" +
                                format_real(model.origin[a]) + ", " + format_real(model.upper(a)) +
                                "] on axis " + std::to_string(a) + " (x = " + format_real(xa) + ")");
        if (!std::isfinite(v[p * d + a])) throw InvalidArgument("velocity: contains non-finite values");
      }
      if (!(std::isfinite(vol[p]) && vol[p] > 0)) throw InvalidArgument("volume: expected finite values > 0");
    }
    const mpm::MaterialKind kind = mpm::parse_material(material);
    const mpm::Material mat =
        mpm::make_material(d, kind, density, youngs_modulus, poisson_ratio, friction_angle, cohesion);
    std::vector<Scalar> mass(vol, vol + m);
    for (Scalar& w : mass) w *= density;
    // A new State (old views keep the old one alive) and a new solver for the new material table.
    auto next = std::make_shared<mpm::State>(*state);
    mpm::Model next_model = model;
    next_model.materials.push_back(mat);
    next->append(x, v, m, mass.data(), vol, static_cast<Index>(next_model.materials.size() - 1));
    solver = std::make_unique<mpm::Solver>(next_model, config);
    model = std::move(next_model);
    const Index start = state->n;
    state = std::move(next);
    return py::make_tuple(start, state->n);
  }

  void add_collider(const std::string& shape, std::vector<Scalar> lower, std::vector<Scalar> upper,
                    std::vector<Scalar> center, Scalar radius, const std::string& boundary, Scalar friction) {
    mpm::Collider c;
    const size_t d = static_cast<size_t>(model.dim);
    if (shape == "box") {
      c.shape = mpm::Collider::Shape::Box;
      if (lower.size() != d || upper.size() != d)
        throw InvalidArgument("region: a box needs 'lower' and 'upper' with " + std::to_string(d) + " coordinates");
      std::copy(lower.begin(), lower.end(), c.lower.begin());
      std::copy(upper.begin(), upper.end(), c.upper.begin());
    } else if (shape == "sphere") {
      c.shape = mpm::Collider::Shape::Sphere;
      if (center.size() != d)
        throw InvalidArgument("region: a sphere needs a 'center' with " + std::to_string(d) + " coordinates");
      std::copy(center.begin(), center.end(), c.center.begin());
      c.radius = radius;
    } else {
      throw InvalidArgument("region: 'shape' must be 'box' or 'sphere', got '" + shape + "'");
    }
    c.boundary = mpm::parse_boundary(boundary, "boundary");
    c.friction = friction;
    mpm::Model next = model;
    mpm::add_collider(next, c);
    solver = std::make_unique<mpm::Solver>(next, config);
    model = std::move(next);
  }

  py::dict step(Scalar dt) {
    mpm::StepStats stats;
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      stats = with_rollback(*state, [&] { return solver->step(*state, dt, interrupt); });
    }
    return to_dict(stats);
  }

  // Steps of stable_dt(cfl) until `duration` has passed; Ctrl-C is checked between steps.
  py::tuple advance(Scalar duration, Scalar cfl) {
    if (!(std::isfinite(duration) && duration >= 0))
      throw InvalidArgument("duration: expected a finite time >= 0 [s], got " + format_real(duration));
    if (!(std::isfinite(cfl) && cfl > 0)) throw InvalidArgument("cfl: expected a number > 0, got " + format_real(cfl));
    Index steps = 0;
    mpm::StepStats last, sum;
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      const Scalar end = state->time + duration;
      while (state->time < end) {
        interrupt.check();
        Scalar dt = solver->stable_dt(*state, cfl);
        const Scalar remaining = end - state->time;
        // Stretch the last step a little rather than leave a sliver.
        if (dt >= remaining || remaining - dt < 0.1 * dt) dt = remaining;
        last = with_rollback(*state, [&] { return solver->step(*state, dt, interrupt); });
        sum.sort_seconds += last.sort_seconds;
        sum.p2g_seconds += last.p2g_seconds;
        sum.grid_seconds += last.grid_seconds;
        sum.g2p_seconds += last.g2p_seconds;
        sum.seconds += last.seconds;
        ++steps;
        if (dt == remaining) state->time = end;
      }
    }
    last.sort_seconds = sum.sort_seconds;
    last.p2g_seconds = sum.p2g_seconds;
    last.grid_seconds = sum.grid_seconds;
    last.g2p_seconds = sum.g2p_seconds;
    last.seconds = sum.seconds;
    return py::make_tuple(steps, to_dict(last));
  }

  static py::dict to_dict(const mpm::StepStats& s) {
    py::dict d;
    d["dt"] = s.dt;
    d["max_speed"] = s.max_speed;
    d["particle_blocks"] = s.particle_blocks;
    d["active_blocks"] = s.active_blocks;
    d["sort_seconds"] = s.sort_seconds;
    d["p2g_seconds"] = s.p2g_seconds;
    d["grid_seconds"] = s.grid_seconds;
    d["g2p_seconds"] = s.g2p_seconds;
    d["seconds"] = s.seconds;
    return d;
  }

  // A writable view of one State buffer, owned by the State through a capsule.
  template <class T>
  py::array view(std::vector<T>& buffer, std::vector<py::ssize_t> shape) const {
    auto* owner = new std::shared_ptr<mpm::State>(state);
    py::capsule capsule(owner, [](void* p) { delete static_cast<std::shared_ptr<mpm::State>*>(p); });
    return py::array_t<T>(shape, buffer.data(), capsule);
  }

  mpm::Model model;
  mpm::Config config;
  std::shared_ptr<mpm::State> state;
  std::unique_ptr<mpm::Solver> solver;
};

}  // namespace

void bind_mpm(py::module_& m) {
  py::class_<PySimulation>(m, "Simulation")
      .def(py::init<std::vector<Index>, Scalar, std::vector<Scalar>, const std::string&, std::vector<Scalar>,
                    Scalar, Scalar, Scalar>(),
           py::arg("shape"), py::arg("h"), py::arg("gravity"), py::arg("boundary"), py::arg("origin"),
           py::arg("friction"),
           py::arg("max_cells_per_step"), py::arg("max_dt"))
      .def("add_particles", &PySimulation::add_particles, py::arg("positions"), py::arg("material"),
           py::arg("density"), py::arg("youngs_modulus"), py::arg("poisson_ratio"), py::arg("velocity"),
           py::arg("volume"), py::arg("friction_angle"), py::arg("cohesion"))
      .def("add_collider", &PySimulation::add_collider, py::arg("shape"), py::arg("lower"), py::arg("upper"),
           py::arg("center"), py::arg("radius"), py::arg("boundary"), py::arg("friction"))
      .def("step", &PySimulation::step, py::arg("dt"))
      .def("advance", &PySimulation::advance, py::arg("duration"), py::arg("cfl"))
      .def("stable_dt", [](const PySimulation& s, Scalar cfl) { return s.solver->stable_dt(*s.state, cfl); },
           py::arg("cfl"))
      .def("kinetic_energy", [](const PySimulation& s) { return s.solver->kinetic_energy(*s.state); })
      .def("momentum", [](const PySimulation& s) { return s.solver->momentum(*s.state); })
      .def("angular_momentum", [](const PySimulation& s) { return s.solver->angular_momentum(*s.state); })
      .def_property_readonly("dim", &PySimulation::dim)
      .def_property_readonly("count", [](const PySimulation& s) { return s.state->n; })
      .def_property_readonly("x", [](PySimulation& s) { return s.view(s.state->x, {s.state->n, s.dim()}); })
      .def_property_readonly("v", [](PySimulation& s) { return s.view(s.state->v, {s.state->n, s.dim()}); })
      .def_property_readonly("F", [](PySimulation& s) {
        return s.view(s.state->F, {s.state->n, s.dim(), s.dim()});
      })
      .def_property_readonly("C", [](PySimulation& s) {
        return s.view(s.state->C, {s.state->n, s.dim(), s.dim()});
      })
      .def_property_readonly("mass", [](PySimulation& s) { return s.view(s.state->mass, {s.state->n}); })
      .def_property_readonly("volume", [](PySimulation& s) { return s.view(s.state->volume, {s.state->n}); })
      .def_property_readonly("material", [](PySimulation& s) { return s.view(s.state->material, {s.state->n}); })
      .def_property_readonly("Jp", [](PySimulation& s) { return s.view(s.state->Jp, {s.state->n}); })
      .def_property("time", [](const PySimulation& s) { return s.state->time; },
                    [](PySimulation& s, Scalar t) { s.state->time = t; })
      .def_property("steps", [](const PySimulation& s) { return s.state->steps; },
                    [](PySimulation& s, Index n) { s.state->steps = n; })
      .def_property_readonly("materials", [](const PySimulation& s) {
        py::list out;
        for (const auto& mat : s.model.materials) {
          py::dict d;
          d["kind"] = mpm::material_name(mat.kind);
          d["density"] = mat.density;
          d["youngs_modulus"] = mat.youngs_modulus;
          d["poisson_ratio"] = mat.poisson_ratio;
          d["mu"] = mat.mu;
          d["lambda"] = mat.lambda;
          d["friction_angle"] = mat.friction_angle;
          d["cohesion"] = mat.cohesion;
          d["wave_speed"] = mat.wave_speed;
          out.append(d);
        }
        return out;
      });
}

}  // namespace kinema::bind
