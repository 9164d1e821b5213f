// kinema._core.grid: the MAC-grid fluid solver behind km.grid. State arrays are handed out as
// writable numpy views of the solver's own memory, each keeping the solver alive; the solver
// never reallocates them. Axes: user axis c is the solver's internal axis c + 3 - dim.
#include <cmath>
#include <cstdint>

#include "bindings/common.h"
#include "fluid/fluid.h"

namespace kinema::bind {

namespace {

using fluid::AdvectionScheme;
using fluid::FluidConfig;
using fluid::FluidSolver;
using fluid::Vec3;

AdvectionScheme parse_scheme(const std::string& name) {
  if (name == "semi_lagrangian") return AdvectionScheme::SemiLagrangian;
  if (name == "maccormack") return AdvectionScheme::MacCormack;
  if (name == "bfecc") return AdvectionScheme::BFECC;
  throw InvalidArgument("scheme: expected 'semi_lagrangian', 'maccormack' or 'bfecc', got '" + name + "'");
}

fluid::AdvectionKernel parse_advection_kernel(const std::string& name) {
  if (name == "auto") return fluid::AdvectionKernel::Auto;
  if (name == "nodes") return fluid::AdvectionKernel::Nodes;
  if (name == "rows") return fluid::AdvectionKernel::Rows;
  if (name == "rows_avx2") return fluid::AdvectionKernel::RowsAvx2;
  throw InvalidArgument("advection_kernel: expected 'auto', 'nodes', 'rows' or 'rows_avx2', got '" + name + "'");
}

int internal_axis(int dim, int user_axis) { return user_axis + 3 - dim; }

Vec3 to_internal(int dim, const std::vector<Scalar>& v, const char* name) {
  if (static_cast<int>(v.size()) != dim)
    throw InvalidArgument(std::string(name) + ": expected " + std::to_string(dim) + " components, got " +
                          std::to_string(v.size()));
  Vec3 out{0, 0, 0};
  for (int c = 0; c < dim; ++c) out[internal_axis(dim, c)] = v[c];
  return out;
}

py::dict to_python(const fluid::StepInfo& s) {
  py::dict d;
  d["pressure"] = bind::to_python(s.pressure);
  d["dt"] = s.dt;
  d["cfl"] = s.cfl;
  d["viscosity_iterations"] = s.viscosity_iterations;
  py::dict seconds;
  seconds["advect"] = s.advect;
  seconds["forces"] = s.forces;
  seconds["viscosity"] = s.viscosity;
  seconds["projection"] = s.projection;
  seconds["total"] = s.total;
  d["seconds"] = seconds;
  return d;
}

// A view of `data` with the user-facing shape, owned by `owner`.
py::array view(py::handle owner, Scalar* data, const std::vector<Index>& shape) {
  std::vector<py::ssize_t> dims(shape.begin(), shape.end());
  return py::array_t<Scalar>(dims, data, owner);
}

std::vector<Index> user_dims(const fluid::FieldLayout& L, int dim) {
  return dim == 2 ? std::vector<Index>{L.n[1], L.n[2]} : std::vector<Index>{L.n[0], L.n[1], L.n[2]};
}

struct PyFluid {
  PyFluid(const std::vector<Index>& shape, Scalar h, const std::string& advection, int rk_order,
          const std::string& projection, Scalar tol, Index max_iter, Scalar viscosity,
          const std::string& boundary, const std::string& walls, const std::vector<Scalar>& gravity,
          bool density, bool temperature, Scalar alpha, Scalar beta, Scalar confinement,
          const std::string& advection_kernel, const std::vector<std::string>& open)
      : shape_(shape) {
    const int dim = shape_.dim;
    FluidConfig c;
    c.advection = parse_scheme(advection);
    c.rk_order = rk_order;
    c.projection = parse_poisson_method(projection);
    c.tol = tol;
    c.max_iter = max_iter;
    c.viscosity = viscosity;
    if (boundary != "closed" && boundary != "periodic")
      throw InvalidArgument("boundary: expected 'closed' or 'periodic', got '" + boundary + "'");
    c.periodic = boundary == "periodic";
    if (walls != "free_slip" && walls != "no_slip")
      throw InvalidArgument("walls: expected 'free_slip' or 'no_slip', got '" + walls + "'");
    c.no_slip = walls == "no_slip";
    c.gravity = gravity.empty() ? Vec3{0, 0, 0} : to_internal(dim, gravity, "gravity");
    c.density = density;
    c.temperature = temperature;
    c.alpha = alpha;
    c.beta = beta;
    c.vorticity_confinement = confinement;
    c.advection_kernel = parse_advection_kernel(advection_kernel);
    for (const std::string& side : open) {
      const std::string sides = dim == 3 ? "x-, x+, y-, y+, z-, z+" : "x-, x+, y-, y+";
      const int user_axis = side.size() == 2 ? side[0] - 'x' : -1;
      if (user_axis < 0 || user_axis >= dim || (side[1] != '-' && side[1] != '+'))
        throw InvalidArgument("open: expected sides among " + sides + ", got '" + side + "'");
      c.open[2 * internal_axis(dim, user_axis) + (side[1] == '+' ? 1 : 0)] = true;
    }
    // Buoyancy acts against gravity, or along +y without it.
    const Scalar g = std::sqrt(c.gravity[0] * c.gravity[0] + c.gravity[1] * c.gravity[1] +
                               c.gravity[2] * c.gravity[2]);
    if (g > 0) c.up = Vec3{-c.gravity[0] / g, -c.gravity[1] / g, -c.gravity[2] / g};
    else c.up[internal_axis(dim, 1)] = 1;
    ReleaseGil release;
    solver_ = std::make_unique<FluidSolver>(shape_, h, c);
  }

  py::dict step(Scalar dt) {
    fluid::StepInfo info;
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      info = solver_->step(dt, interrupt);
    }
    return to_python(info);
  }

  py::tuple advance(Scalar duration, Scalar cfl) {
    fluid::StepInfo info;
    Index steps = 0;
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      steps = solver_->advance(duration, cfl, interrupt, &info);
    }
    return py::make_tuple(steps, steps > 0 ? py::object(to_python(info)) : py::object(py::none()));
  }

  void set_wall_velocity(int user_axis, int side, const std::vector<Scalar>& velocity) {
    const int dim = shape_.dim;
    const int axis = internal_axis(dim, user_axis);
    solver_->set_wall_velocity(2 * axis + side, to_internal(dim, velocity, "velocity"));
  }

  Index add_source(py::array_t<std::uint8_t, py::array::c_style | py::array::forcecast> mask, py::object density,
                   py::object temperature, py::object velocity) {
    const int dim = shape_.dim;
    if (static_cast<Index>(mask.size()) != shape_.size())
      throw InvalidArgument("region: expected a bool array of the grid's shape");
    Vec3 vel{0, 0, 0};
    if (!velocity.is_none()) vel = to_internal(dim, velocity.cast<std::vector<Scalar>>(), "velocity");
    const std::uint8_t* m = mask.data();
    const bool set_d = !density.is_none(), set_t = !temperature.is_none(), set_v = !velocity.is_none();
    const Scalar d = set_d ? density.cast<Scalar>() : 0, t = set_t ? temperature.cast<Scalar>() : 0;
    ReleaseGil release;
    return solver_->add_source(m, set_d, d, set_t, t, set_v, vel);
  }

  py::array_t<Scalar> divergence() {
    std::vector<Scalar> out(shape_.size());
    {
      ReleaseGil release;
      solver_->divergence(out.data());
    }
    return to_numpy(std::move(out), shape_.user_shape());
  }

  py::array_t<Scalar> velocity_at(py::array points) {
    const int dim = shape_.dim;
    if (points.ndim() != 2 || points.shape(1) != dim)
      throw InvalidArgument("points: expected shape (M, " + std::to_string(dim) + ")");
    const Index m = points.shape(0);
    const Scalar* x = checked_data(points, "points", m * dim, false);
    std::vector<Scalar> out(m * dim);
    {
      ReleaseGil release;
      parallel_for(m, [&](Index p) {
        Vec3 q{0, 0, 0};
        for (int c = 0; c < dim; ++c) q[internal_axis(dim, c)] = x[p * dim + c];
        const Vec3 v = solver_->velocity_at(q);
        for (int c = 0; c < dim; ++c) out[p * dim + c] = v[internal_axis(dim, c)];
      });
    }
    return to_numpy(std::move(out), {m, dim});
  }

  GridShape shape_;
  std::unique_ptr<FluidSolver> solver_;
};

}  // namespace

void bind_grid(py::module_& m) {
  py::class_<PyFluid>(m, "Fluid")
      .def(py::init<const std::vector<Index>&, Scalar, const std::string&, int, const std::string&, Scalar,
                    Index, Scalar, const std::string&, const std::string&, const std::vector<Scalar>&, bool,
                    bool, Scalar, Scalar, Scalar, const std::string&, const std::vector<std::string>&>(),
           py::arg("shape"), py::arg("h"), py::arg("advection"), py::arg("rk_order"), py::arg("projection"),
           py::arg("tol"), py::arg("max_iter"), py::arg("viscosity"), py::arg("boundary"), py::arg("walls"),
           py::arg("gravity"), py::arg("density"), py::arg("temperature"), py::arg("alpha"), py::arg("beta"),
           py::arg("vorticity_confinement"), py::arg("advection_kernel"), py::arg("open"))
      .def("step", &PyFluid::step, py::arg("dt"))
      .def("advance", &PyFluid::advance, py::arg("duration"), py::arg("cfl"))
      .def("set_wall_velocity", &PyFluid::set_wall_velocity, py::arg("axis"), py::arg("side"),
           py::arg("velocity"))
      .def("add_source", &PyFluid::add_source, py::arg("mask"), py::arg("density"), py::arg("temperature"),
           py::arg("velocity"))
      .def("clear_sources", [](PyFluid& f) { f.solver_->clear_sources(); })
      .def_property_readonly("source_count", [](const PyFluid& f) {
        return static_cast<Index>(f.solver_->model().sources.size());
      })
      .def("divergence", &PyFluid::divergence)
      .def("velocity_at", &PyFluid::velocity_at, py::arg("points"))
      .def("kinetic_energy", [](const PyFluid& f) { return f.solver_->kinetic_energy(); })
      .def("max_speed", [](const PyFluid& f) { return f.solver_->max_speed(); })
      .def("velocity", [](py::object self, int user_axis) {
        PyFluid& f = self.cast<PyFluid&>();
        const int dim = f.shape_.dim;
        if (user_axis < 0 || user_axis >= dim) throw InvalidArgument("axis: no such velocity component");
        const int a = internal_axis(dim, user_axis);
        return view(self, f.solver_->state().velocity[a].data(), user_dims(f.solver_->face(a), dim));
      })
      .def_property_readonly("pressure", [](py::object self) {
        PyFluid& f = self.cast<PyFluid&>();
        return view(self, f.solver_->state().pressure.data(), f.shape_.user_shape());
      })
      .def("scalar", [](py::object self, const std::string& name) -> py::object {
        PyFluid& f = self.cast<PyFluid&>();
        auto& q = name == "density" ? f.solver_->state().density : f.solver_->state().temperature;
        if (q.empty()) return py::none();
        return view(self, q.data(), f.shape_.user_shape());
      })
      .def_property_readonly("solid", [](py::object self) {
        PyFluid& f = self.cast<PyFluid&>();
        const auto dims = f.shape_.user_shape();
        std::vector<py::ssize_t> shape(dims.begin(), dims.end()), strides(dims.size());
        py::ssize_t stride = 1;
        for (size_t i = dims.size(); i-- > 0;) {
          strides[i] = stride;
          stride *= shape[i];
        }
        return py::array(py::dtype::of<bool>(), shape, strides, f.solver_->model().solid.data(), self);
      })
      // Settable for checkpoints (km.Scene resumes a run bit for bit).
      .def_property("time", [](const PyFluid& f) { return f.solver_->state().time; },
                    [](PyFluid& f, Scalar t) { f.solver_->state().time = t; })
      .def_property("steps", [](const PyFluid& f) { return f.solver_->state().steps; },
                    [](PyFluid& f, Index n) { f.solver_->state().steps = n; });

  m.def("advect", [](py::array q, std::vector<py::array> velocity, Scalar dt, Scalar h, const std::string& scheme,
                     int rk_order, bool periodic) {
    const std::vector<Index> user = shape_of(q);
    const GridShape shape(user);
    const int dim = shape.dim;
    if (static_cast<int>(velocity.size()) != dim)
      throw InvalidArgument("velocity: expected " + std::to_string(dim) + " MAC components");
    if (rk_order < 1 || rk_order > 3) throw InvalidArgument("rk_order: expected 1, 2 or 3");
    const AdvectionScheme s = parse_scheme(scheme);
    fluid::MacVelocity u;
    for (int a = 0; a < 3; ++a) u.layout[a] = fluid::face_layout(shape, a, periodic);
    for (int c = 0; c < dim; ++c) {
      const int a = internal_axis(dim, c);
      static const char* names[3] = {"velocity[0]", "velocity[1]", "velocity[2]"};
      u.comp[a] = checked_data(velocity[c], names[c], u.layout[a].size(), false);
    }
    const Scalar* qp = checked_data(q, "q", shape.size(), false);
    std::vector<Scalar> out(shape.size());
    {
      ReleaseGil release;
      fluid::AdvectionScratch scratch;
      fluid::advect(s, u, fluid::cell_layout(shape, periodic), qp, out.data(), dt / h, rk_order, scratch);
    }
    return to_numpy(std::move(out), user);
  });
}

}  // namespace kinema::bind
