// kinema._core.grid: the MAC-grid fluid solver behind km.grid. Config and StepStats are bound as
// objects (one new option or statistic is one edit); the Fluid object holds the Solver and its
// State, whose arrays are handed out as writable numpy views, each keeping the Fluid alive; they
// are never reallocated (set_state copies into them). Axes: user axis c is the solver's internal
// axis c + 3 - dim.
#include <cmath>
#include <cstdint>
#include <memory>
#include <limits>

#include "bindings/common.h"
#include "grid/solver.h"

namespace kinema::bind {

namespace {

using grid::AdvectionKernel;
using grid::AdvectionScheme;
using grid::Vec3;

int internal_axis(int dim, int user_axis) { return user_axis + 3 - dim; }

Vec3 to_internal(int dim, const std::vector<Scalar>& v, const char* name) {
  if (static_cast<int>(v.size()) != dim)
    throw InvalidArgument(std::string(name) + ": expected " + std::to_string(dim) + " components, got " +
                          std::to_string(v.size()));
  Vec3 out{0, 0, 0};
  for (int c = 0; c < dim; ++c) out[internal_axis(dim, c)] = v[c];
  return out;
}

// A view of `data` with the user-facing shape, owned by `owner`.
py::array view(py::handle owner, Scalar* data, const std::vector<Index>& shape) {
  std::vector<py::ssize_t> dims(shape.begin(), shape.end());
  return py::array_t<Scalar>(dims, data, owner);
}

std::vector<Index> user_dims(const grid::FieldLayout& L, int dim) {
  return dim == 2 ? std::vector<Index>{L.n[1], L.n[2]} : std::vector<Index>{L.n[0], L.n[1], L.n[2]};
}

// The advection scratch one forward step left (Fluid.step_keep), for that step's adjoint.
struct AdvectionKept {
  std::array<grid::AdvectionScratch, 4> scratch;
};

// The Solver and the State it advances, as one Python object.
struct PyFluid {
  PyFluid(const std::vector<Index>& shape, Scalar h, const grid::Config& config) : shape_(shape) {
    ReleaseGil release;
    solver_ = std::make_unique<grid::Solver>(grid::make_model(shape_, h), config);
    state_ = solver_->make_state();
  }

  grid::StepStats step(Scalar dt, const py::object& control) {
    py::object holder;
    const Scalar* u = read_control(control, holder);
    Interrupt interrupt = python_interrupt();
    ReleaseGil release;
    return solver_->step(state_, dt, interrupt, u);
  }

  // step(dt, control) that also returns its advection scratch, for step_adjoint's `forward`:
  // into `reuse` when given (a spent one: its arrays are refilled, not allocated again).
  py::object step_keep(Scalar dt, const py::object& control, py::object reuse) {
    py::object holder;
    const Scalar* u = read_control(control, holder);
    if (reuse.is_none()) reuse = py::cast(AdvectionKept{});
    AdvectionKept& kept = reuse.cast<AdvectionKept&>();
    Interrupt interrupt = python_interrupt();
    ReleaseGil release;
    solver_->step(state_, dt, interrupt, u, &kept.scratch);
    return reuse;
  }

  // A control of one value per cell and velocity component, or nullptr for None: read in place
  // when `control` is a C-contiguous float64 array (held by `holder` while it is read), else
  // converted once into `holder`; checked finite.
  const Scalar* read_control(const py::object& control, py::object& holder) const {
    if (control.is_none()) return nullptr;
    const Index size = shape_.size() * shape_.dim;
    const auto a = py::array_t<Scalar, py::array::c_style | py::array::forcecast>::ensure(control);
    if (!a || a.size() != size)
      throw InvalidArgument("control: expected a float array of shape (*shape, " + std::to_string(shape_.dim) +
                            ") with " + std::to_string(size) + " values");
    holder = a;
    const Scalar* data = a.data();
    for (Index i = 0; i < size; ++i)
      if (!std::isfinite(data[i])) throw InvalidArgument("control: expected finite accelerations");
    return data;
  }

  // Copies the arrays named in `d` (u, v[, w], pressure, density, temperature: user names and
  // shapes) into a state made by the solver; names left out are zero when `missing_zero`.
  grid::State read_state(const py::dict& d, bool missing_zero) const {
    grid::State out;
    const int dim = shape_.dim;
    const grid::Config& config = solver_->config();
    // each array of make_state's size, written once (from the dict, or zero when missing)
    auto read = [&](const std::string& key, std::vector<Scalar>& dst, Index size) {
      if (size == 0) return;
      if (!d.contains(key)) {
        if (!missing_zero) throw InvalidArgument("state: missing key '" + key + "'");
        dst.assign(static_cast<size_t>(size), 0);
        return;
      }
      const auto a = py::array_t<Scalar, py::array::c_style | py::array::forcecast>::ensure(d[key.c_str()]);
      if (!a || static_cast<Index>(a.size()) != size)
        throw InvalidArgument("state['" + key + "']: expected " + std::to_string(size) + " float values");
      dst.assign(a.data(), a.data() + a.size());
    };
    const Index cells = shape_.size();
    for (int c = 0; c < dim; ++c) {
      const int a = internal_axis(dim, c);
      read(std::string(1, "uvw"[c]), out.velocity[a], solver_->face(a).size());
    }
    read("pressure", out.pressure, cells);
    read("density", out.density, config.density ? cells : 0);
    read("temperature", out.temperature, config.temperature ? cells : 0);
    if (!missing_zero) {
      if (d.contains("time")) out.time = d["time"].cast<Scalar>();
      if (d.contains("steps")) out.steps = d["steps"].cast<Index>();
    }
    return out;
  }

  // The arrays of `s` (spent: its vectors are moved into the arrays, not copied) by user name.
  py::dict write_state(grid::State&& s) const {
    py::dict out;
    const int dim = shape_.dim;
    for (int c = 0; c < dim; ++c) {
      const int a = internal_axis(dim, c);
      out[py::str(std::string(1, "uvw"[c]))] =
          to_numpy(std::move(s.velocity[a]), user_dims(solver_->face(a), dim));
    }
    if (!s.density.empty()) out["density"] = to_numpy(std::move(s.density), shape_.user_shape());
    if (!s.temperature.empty())
      out["temperature"] = to_numpy(std::move(s.temperature), shape_.user_shape());
    return out;
  }

  // (dL/d(before) as a dict, dL/dviscosity or None when not wanted, dL/dcontrol or None) of one
  // step from `before`.
  // warm_start: the pressure solve may start from the last call's solution when that was the
  // adjoint of the next step (km.diff's backward chain, reset by reset_adjoint_warm_start at its
  // start); else from zero, so a lone call's bits do not depend on the calls before it.
  py::tuple step_adjoint(Scalar dt, const py::dict& before, const py::object& control, const py::dict& grads,
                         bool want_viscosity, const AdvectionKept* forward, bool warm_start) {
    const grid::State b = read_state(before, false);
    grid::State adjoint = read_state(grads, true);
    py::object holder;
    const Scalar* u = read_control(control, holder);
    std::vector<Scalar> grad_control(u ? static_cast<size_t>(shape_.size() * shape_.dim) : 0);
    Scalar grad_viscosity = 0;
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      if (!warm_start) solver_->reset_adjoint_warm_start();
      solver_->step_adjoint(b, dt, u, adjoint, want_viscosity ? &grad_viscosity : nullptr,
                            u ? grad_control.data() : nullptr, interrupt, forward ? &forward->scratch : nullptr);
    }
    py::object gc = py::none();
    if (u) {
      std::vector<Index> dims = shape_.user_shape();
      dims.push_back(shape_.dim);
      gc = to_numpy(std::move(grad_control), dims);
    }
    return py::make_tuple(write_state(std::move(adjoint)), want_viscosity ? py::object(py::float_(grad_viscosity)) : py::none(),
                          gc);
  }

  // The projection's transpose applied to the velocity gradients of `grads` (tests).
  py::dict projection_adjoint(Scalar dt, const py::dict& grads) {
    grid::State adjoint = read_state(grads, true);
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      solver_->projection_adjoint(adjoint.velocity, dt, interrupt);
    }
    return write_state(std::move(adjoint));
  }

  py::tuple advance(Scalar duration, Scalar cfl, Scalar max_dt) {
    grid::StepStats last;
    Index steps = 0;
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      steps = solver_->advance(state_, duration, cfl, max_dt, interrupt, &last).steps;
    }
    return py::make_tuple(steps, steps > 0 ? py::cast(last) : py::object(py::none()));
  }

  void set_wall_velocity(int user_axis, int side, const std::vector<Scalar>& velocity) {
    const int dim = shape_.dim;
    if (user_axis < 0 || user_axis >= dim || side < 0 || side > 1)
      throw InvalidArgument("side: no such wall in a " + std::to_string(dim) + "D domain");
    solver_->set_wall_velocity(2 * internal_axis(dim, user_axis) + side, to_internal(dim, velocity, "velocity"));
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
      solver_->divergence(state_, out.data());
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
        const Vec3 v = solver_->velocity_at(state_, q);
        for (int c = 0; c < dim; ++c) out[p * dim + c] = v[internal_axis(dim, c)];
      });
    }
    return to_numpy(std::move(out), {m, dim});
  }

  GridShape shape_;
  std::unique_ptr<grid::Solver> solver_;
  grid::State state_;
};

// A run kept whole for km.diff (Fluid._diff_record): the steps' states and controls, stepped
// and reversed in C++ by the same calls as _diff_step and _diff_step_adjoint (the same bits),
// without a Python round trip per step.
struct PyRecord {
  py::object owner;  // the PyFluid
  PyFluid* fluid = nullptr;
  Scalar dt = 0;
  Index steps = 0;
  std::vector<grid::State> states;  // before step k, k = 0..steps
  std::vector<Scalar> controls;     // steps x cells x dim, or empty
  std::vector<AdvectionKept> kept;  // each step's advection scratch, or empty (recomputed)

  // (dL/d(initial state) as a dict, dL/dviscosity summed over the steps or None when not
  // wanted, dL/dcontrols of shape (steps, *shape, dim) or None).
  py::tuple backward(const py::dict& grads, bool want_viscosity) {
    grid::State adjoint = fluid->read_state(grads, true);
    const Index per_step = fluid->shape_.size() * fluid->shape_.dim;
    std::vector<Scalar> grad_controls(controls.empty() ? 0 : static_cast<size_t>(steps * per_step));
    Scalar grad_viscosity = 0;
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      fluid->solver_->reset_adjoint_warm_start();  // a chain of its own steps only
      for (Index k = steps - 1; k >= 0; --k) {
        Scalar g = 0;
        const Scalar* u = controls.empty() ? nullptr : controls.data() + k * per_step;
        fluid->solver_->step_adjoint(states[k], dt, u, adjoint, want_viscosity ? &g : nullptr,
                                     u ? grad_controls.data() + k * per_step : nullptr, interrupt,
                                     kept.empty() ? nullptr : &kept[k].scratch);
        grad_viscosity = k == steps - 1 ? g : grad_viscosity + g;  // km.diff's order of the sum
      }
    }
    py::object gc = py::none();
    if (!controls.empty()) {
      std::vector<Index> dims = fluid->shape_.user_shape();
      dims.insert(dims.begin(), steps);
      dims.push_back(fluid->shape_.dim);
      gc = to_numpy(std::move(grad_controls), dims);
    }
    return py::make_tuple(fluid->write_state(std::move(adjoint)),
                          want_viscosity ? py::object(py::float_(grad_viscosity)) : py::none(), gc);
  }
};

// `steps` steps of dt from the fluid's state with controls (None or steps x cells x dim values),
// each state kept (and each step's advection scratch when keep_scratch); the fluid ends at the
// last one.
PyRecord record_run(py::object self, Scalar dt, Index steps, const py::object& controls, bool keep_scratch) {
  PyFluid& f = self.cast<PyFluid&>();
  if (steps < 0) throw InvalidArgument("steps: expected a count >= 0");
  PyRecord rec;
  rec.owner = self;
  rec.fluid = &f;
  rec.dt = dt;
  rec.steps = steps;
  const Index per_step = f.shape_.size() * f.shape_.dim;
  if (!controls.is_none()) {
    const auto a = py::array_t<Scalar, py::array::c_style | py::array::forcecast>::ensure(controls);
    if (!a || a.size() != steps * per_step)
      throw InvalidArgument("controls: expected a float array of shape (steps, *shape, " +
                            std::to_string(f.shape_.dim) + ")");
    rec.controls.assign(a.data(), a.data() + a.size());
    for (Scalar x : rec.controls)
      if (!std::isfinite(x)) throw InvalidArgument("control: expected finite accelerations");
  }
  rec.states.reserve(static_cast<size_t>(steps + 1));
  Interrupt interrupt = python_interrupt();
  ReleaseGil release;
  rec.states.push_back(f.state_);
  if (keep_scratch) rec.kept.resize(static_cast<size_t>(steps));
  for (Index k = 0; k < steps; ++k) {
    f.solver_->step(f.state_, dt, interrupt, rec.controls.empty() ? nullptr : rec.controls.data() + k * per_step,
                    keep_scratch ? &rec.kept[k].scratch : nullptr);
    rec.states.push_back(f.state_);
  }
  return rec;
}

}  // namespace

void bind_grid(py::module_& m) {
  py::enum_<AdvectionScheme>(m, "AdvectionScheme", "Advection scheme (kernels.h).")
      .value("semi_lagrangian", AdvectionScheme::SemiLagrangian)
      .value("maccormack", AdvectionScheme::MacCormack)
      .value("bfecc", AdvectionScheme::BFECC);
  py::enum_<AdvectionKernel>(m, "AdvectionKernel", "Implementation of the advection (same results).")
      .value("auto", AdvectionKernel::Auto)
      .value("nodes", AdvectionKernel::Nodes)
      .value("rows", AdvectionKernel::Rows)
      .value("rows_avx2", AdvectionKernel::RowsAvx2);

  using grid::Config;
  py::class_<Config>(m, "Config", "Parameters of a MAC-grid fluid (grid/config.h); vectors on internal axes.")
      .def(py::init<>())
      .def_readwrite("advection", &Config::advection)
      .def_readwrite("rk_order", &Config::rk_order, "back-trace order, 1-3")
      .def_readwrite("advection_kernel", &Config::advection_kernel)
      .def_readwrite("projection", &Config::projection, "kinema._core.poisson.Method of the pressure solve")
      .def_readwrite("tol", &Config::tol, "relative residual of the pressure solve")
      .def_readwrite("max_iter", &Config::max_iter, "0: the solver's default")
      .def_readwrite("pressure_vcycles", &Config::pressure_vcycles,
                     "0: solve the pressure to tol; k > 0: exactly k multigrid V-cycles from zero")
      .def_readwrite("viscosity", &Config::viscosity, "kinematic viscosity [m^2/s]")
      .def_readwrite("periodic", &Config::periodic)
      .def_readwrite("no_slip", &Config::no_slip)
      .def_readwrite("open", &Config::open, "open sides, wall 2*axis + side (internal axes)")
      .def_readwrite("gravity", &Config::gravity, "[m/s^2], internal axes")
      .def_readwrite("density", &Config::density)
      .def_readwrite("temperature", &Config::temperature)
      .def_readwrite("alpha", &Config::alpha, "buoyancy -alpha * density [m/s^2 per unit]")
      .def_readwrite("beta", &Config::beta, "buoyancy beta * temperature [m/s^2 per unit]")
      .def_readwrite("up", &Config::up, "buoyancy direction, internal axes (0: against gravity, else +y)")
      .def_readwrite("vorticity_confinement", &Config::vorticity_confinement);

  using grid::StepStats;
  py::class_<StepStats, StepStatsBase>(m, "StepStats",
                                       "What one step did: the pressure solve, the CFL number max|u| dt / h "
                                       "before it, the viscosity's CG iterations and the seconds per phase.")
      .def_property_readonly("pressure", [](const StepStats& s) { return to_python(s.pressure); },
                             "the projection's pressure solve (SolveInfo)")
      .def_readonly("cfl", &StepStats::cfl)
      .def_readonly("viscosity_iterations", &StepStats::viscosity_iterations)
      .def_readonly("advect_seconds", &StepStats::advect_seconds)
      .def_readonly("forces_seconds", &StepStats::forces_seconds)
      .def_readonly("viscosity_seconds", &StepStats::viscosity_seconds)
      .def_readonly("projection_seconds", &StepStats::projection_seconds);

  py::class_<AdvectionKept>(m, "AdvectionKept", "A forward step's advection scratch (Fluid.step_keep), "
                                                 "read by Fluid.step_adjoint instead of recomputing it.");
  py::class_<PyRecord>(m, "FluidRecord")
      .def("backward", &PyRecord::backward, py::arg("grads"), py::arg("want_viscosity"));

  py::class_<PyFluid>(m, "Fluid")
      .def(py::init<const std::vector<Index>&, Scalar, const Config&>(), py::arg("shape"), py::arg("h"),
           py::arg("config"))
      .def_property_readonly("config", [](const PyFluid& f) { return f.solver_->config(); })
      .def("step", &PyFluid::step, py::arg("dt"), py::arg("control") = py::none())
      .def("step_adjoint", &PyFluid::step_adjoint, py::arg("dt"), py::arg("before"), py::arg("control"),
           py::arg("grads"), py::arg("want_viscosity") = true, py::arg("forward") = nullptr,
           py::arg("warm_start") = false)
      .def("reset_adjoint_warm_start", [](PyFluid& f) { f.solver_->reset_adjoint_warm_start(); })
      .def("step_keep", &PyFluid::step_keep, py::arg("dt"), py::arg("control") = py::none(),
           py::arg("reuse") = py::none())
      .def("record", &record_run, py::arg("dt"), py::arg("steps"), py::arg("controls"),
           py::arg("keep_scratch") = false)
      .def("check_differentiable", [](const PyFluid& f) { f.solver_->check_differentiable(); })
      .def("set_viscosity", [](PyFluid& f, Scalar nu) { f.solver_->set_viscosity(nu); }, py::arg("viscosity"))
      .def("project", [](PyFluid& f, Scalar dt) {
        Interrupt interrupt = python_interrupt();
        SolveInfo info;
        {
          ReleaseGil release;
          info = f.solver_->apply_projection(f.state_, dt, interrupt);
        }
        return to_python(info);
      }, py::arg("dt"))
      .def("projection_adjoint", &PyFluid::projection_adjoint, py::arg("dt"), py::arg("grads"))
      .def("advance", &PyFluid::advance, py::arg("duration"), py::arg("cfl"),
           py::arg("max_dt") = std::numeric_limits<Scalar>::infinity())
      .def("stable_dt", [](const PyFluid& f, Scalar cfl, Scalar max_dt) {
        return f.solver_->stable_dt(f.state_, cfl, max_dt);
      }, py::arg("cfl"), py::arg("max_dt") = std::numeric_limits<Scalar>::infinity())
      .def("set_wall_velocity", &PyFluid::set_wall_velocity, py::arg("axis"), py::arg("side"),
           py::arg("velocity"))
      .def("add_source", &PyFluid::add_source, py::arg("mask"), py::arg("density"), py::arg("temperature"),
           py::arg("velocity"))
      .def("clear_sources", [](PyFluid& f) { f.solver_->clear_sources(); })
      .def_property_readonly("source_count", [](const PyFluid& f) {
        return static_cast<Index>(f.solver_->model().sources.size());
      })
      .def("divergence", &PyFluid::divergence)
      .def("multigrid_levels", [](const PyFluid& f) { return f.solver_->multigrid_levels(); })
      .def("velocity_at", &PyFluid::velocity_at, py::arg("points"))
      .def("kinetic_energy", [](const PyFluid& f) { return f.solver_->kinetic_energy(f.state_); })
      .def("max_speed", [](const PyFluid& f) { return f.solver_->max_speed(f.state_); })
      .def("velocity", [](py::object self, int user_axis) {
        PyFluid& f = self.cast<PyFluid&>();
        const int dim = f.shape_.dim;
        if (user_axis < 0 || user_axis >= dim) throw InvalidArgument("axis: no such velocity component");
        const int a = internal_axis(dim, user_axis);
        return view(self, f.state_.velocity[a].data(), user_dims(f.solver_->face(a), dim));
      })
      .def_property_readonly("pressure", [](py::object self) {
        PyFluid& f = self.cast<PyFluid&>();
        return view(self, f.state_.pressure.data(), f.shape_.user_shape());
      })
      .def("scalar", [](py::object self, const std::string& name) -> py::object {
        PyFluid& f = self.cast<PyFluid&>();
        auto& q = name == "density" ? f.state_.density : f.state_.temperature;
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
        return py::array(py::dtype::of<bool>(), shape, strides, f.solver_->solid(), self);
      })
      // Settable for set_state (exact resume).
      .def_property("time", [](const PyFluid& f) { return f.state_.time; },
                    [](PyFluid& f, Scalar t) { f.state_.time = t; })
      .def_property("steps", [](const PyFluid& f) { return f.state_.steps; },
                    [](PyFluid& f, Index n) { f.state_.steps = n; });

  m.def("advect", [](py::array q, std::vector<py::array> velocity, Scalar dt, Scalar h, AdvectionScheme scheme,
                     int rk_order, bool periodic) {
    const std::vector<Index> user = shape_of(q);
    const GridShape shape(user);
    const int dim = shape.dim;
    if (static_cast<int>(velocity.size()) != dim)
      throw InvalidArgument("velocity: expected " + std::to_string(dim) + " MAC components");
    if (rk_order < 1 || rk_order > 3) throw InvalidArgument("rk_order: expected 1, 2 or 3");
    grid::MacVelocity u;
    for (int a = 0; a < 3; ++a) u.layout[a] = grid::face_layout(shape, a, periodic);
    for (int c = 0; c < dim; ++c) {
      const int a = internal_axis(dim, c);
      static const char* names[3] = {"velocity[0]", "velocity[1]", "velocity[2]"};
      u.comp[a] = checked_data(velocity[c], names[c], u.layout[a].size(), false);
    }
    const Scalar* qp = checked_data(q, "q", shape.size(), false);
    std::vector<Scalar> out(shape.size());
    {
      ReleaseGil release;
      grid::AdvectionScratch scratch;
      grid::advect(scheme, u, grid::cell_layout(shape, periodic), qp, out.data(), dt / h, rk_order, scratch);
    }
    return to_numpy(std::move(out), user);
  });
}

}  // namespace kinema::bind
