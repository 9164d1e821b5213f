// kinema._core.sph: the SPH fluid behind km.sph.Fluid, the neighbour search and scene helpers.
// State arrays are zero-copy views of the C++ State whose base is the Fluid object; the State's
// buffers are never reallocated (Morton reordering permutes their rows in place).
#include <optional>

#include "bindings/common.h"
#include "core/errors.h"
#include "particles/neighbor_grid.h"
#include "sph/fluid.h"
#include "sph/kernels.h"

namespace kinema::bind {

namespace {

int dim_of(const py::array& a, const char* name) {
  if (a.ndim() != 2 || (a.shape(1) != 2 && a.shape(1) != 3))
    throw InvalidArgument(std::string(name) + ": expected shape (n, 2) or (n, 3)");
  return static_cast<int>(a.shape(1));
}

struct PyFluid {
  PyFluid(py::array positions, py::array velocities, Scalar spacing, const std::string& method,
          Scalar rho0, Scalar viscosity, std::vector<Scalar> gravity, std::optional<py::array> boundary,
          std::optional<std::vector<Scalar>> lower, std::optional<std::vector<Scalar>> upper,
          Scalar speed_of_sound, Scalar gamma, Scalar tol, Scalar divergence_tol, int max_iter,
          bool divergence_solve, int reorder_every, Scalar neighbor_skin, Scalar warm_start)
      : state(dim_of(positions, "positions"), positions.shape(0)) {
    const int d = state.dim;
    const Scalar* xp = checked_data(positions, "positions", state.n * d, false);
    const Scalar* vp = checked_data(velocities, "velocity", state.n * d, false);
    std::copy(xp, xp + state.n * d, state.x.begin());
    std::copy(vp, vp + state.n * d, state.v.begin());
    std::vector<Scalar> xb;
    if (boundary) {
      if (boundary->ndim() != 2 || boundary->shape(1) != d)
        throw InvalidArgument("boundary: expected shape (M, " + std::to_string(d) + ")");
      const Scalar* bp = checked_data(*boundary, "boundary", boundary->size(), false);
      xb.assign(bp, bp + boundary->size());
    }
    if (gravity.size() != static_cast<size_t>(d))
      throw InvalidArgument("gravity: expected " + std::to_string(d) + " components");
    sph::Config config;
    config.method = sph::parse_method(method);
    config.rho0 = rho0;
    config.viscosity = viscosity;
    config.gravity = {0, 0, 0};
    std::copy(gravity.begin(), gravity.end(), config.gravity.begin());
    config.speed_of_sound = speed_of_sound;
    config.gamma = gamma;
    config.tol = tol;
    config.divergence_tol = divergence_tol;
    config.max_iter = max_iter;
    config.divergence_solve = divergence_solve;
    config.reorder_every = reorder_every;
    config.neighbor_skin = neighbor_skin;
    config.warm_start = warm_start;
    ReleaseGil release;
    const sph::Model model = sph::make_model(d, spacing, rho0, std::move(xb),
                                             lower ? lower->data() : nullptr,
                                             upper ? upper->data() : nullptr);
    solver = sph::Solver::create(model, config, state);
  }

  py::dict step(Scalar dt) {
    sph::StepStats stats;
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      stats = step_or_rollback(dt, interrupt);
    }
    return to_dict(stats);
  }

  // One step; a failing step leaves the state as it was and drops the caches it built.
  sph::StepStats step_or_rollback(Scalar dt, Interrupt& interrupt) {
    check_ids();
    try {
      return with_rollback(state, [&] { return solver->step(state, dt, interrupt); });
    } catch (...) {
      solver->reset_caches();
      throw;
    }
  }

  // Steps of CFL-limited dt until `duration` has passed; Ctrl-C is checked between steps.
  py::tuple advance(Scalar duration, Scalar cfl) {
    Index steps = 0;
    sph::StepStats last;
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      const Scalar end = state.time + duration;
      while (state.time < end) {
        interrupt.check();
        Scalar dt = solver->stable_dt(state, cfl);
        const Scalar remaining = end - state.time;
        // Stretch the last step a little rather than leave a sliver.
        if (dt >= remaining || remaining - dt < 0.1 * dt) dt = remaining;
        last = step_or_rollback(dt, interrupt);
        ++steps;
        if (dt == remaining) state.time = end;
      }
    }
    return py::make_tuple(steps, to_dict(last));
  }

  // The ids view is writable (checkpoints restore it), so a step first checks that it still
  // is a permutation of 0..n-1: the ids label the particles the step moves and reorders.
  void check_ids() const {
    std::vector<char> seen(static_cast<size_t>(state.n), 0);
    for (Index k = 0; k < state.n; ++k) {
      const Index id = state.ids[k];
      if (id < 0 || id >= state.n || seen[id])
        throw InvalidArgument("ids: row " + std::to_string(k) + " holds " + std::to_string(id) +
                              ", which is out of range or repeated; ids must be a permutation of 0.." +
                              std::to_string(state.n - 1));
      seen[id] = 1;
    }
  }

  static py::dict to_dict(const sph::StepStats& s) {
    py::dict d;
    d["dt"] = s.dt;
    d["iterations"] = s.iterations;
    d["divergence_iterations"] = s.divergence_iterations;
    d["density_error"] = s.density_error;
    d["divergence_error"] = s.divergence_error;
    d["max_speed"] = s.max_speed;
    d["neighbor_count"] = s.neighbor_count;
    d["neighbor_rebuild"] = s.neighbor_rebuild;
    d["seconds"] = s.seconds;
    return d;
  }

  sph::State state;
  std::unique_ptr<sph::Solver> solver;
};

// A view of one State buffer whose base is the Fluid object (kept alive by the array).
template <class T>
py::array view(py::object self, std::vector<T>& buffer, std::vector<py::ssize_t> shape) {
  return py::array_t<T>(shape, buffer.data(), self);
}

}  // namespace

void bind_sph(py::module_& m) {
  py::class_<PyFluid>(m, "Fluid")
      .def(py::init<py::array, py::array, Scalar, const std::string&, Scalar, Scalar, std::vector<Scalar>,
                    std::optional<py::array>, std::optional<std::vector<Scalar>>,
                    std::optional<std::vector<Scalar>>, Scalar, Scalar, Scalar, Scalar, int, bool, int,
                    Scalar, Scalar>(),
           py::arg("positions"), py::arg("velocity"), py::arg("spacing"), py::arg("method"),
           py::arg("rho0"), py::arg("viscosity"), py::arg("gravity"), py::arg("boundary"),
           py::arg("lower"), py::arg("upper"), py::arg("speed_of_sound"), py::arg("gamma"),
           py::arg("tol"), py::arg("divergence_tol"), py::arg("max_iter"),
           py::arg("divergence_solve"), py::arg("reorder_every"), py::arg("neighbor_skin"),
           py::arg("warm_start"))
      .def("step", &PyFluid::step, py::arg("dt"))
      .def("advance", &PyFluid::advance, py::arg("duration"), py::arg("cfl"))
      .def("stable_dt", [](const PyFluid& f, Scalar cfl) { return f.solver->stable_dt(f.state, cfl); },
           py::arg("cfl"))
      .def("reset_caches", [](PyFluid& f) { f.solver->reset_caches(); })
      .def("density_error", [](PyFluid& f) {
        ReleaseGil release;
        return f.solver->density_error(f.state);
      })
      // (fluid pairs (P, 2), (fluid, boundary sample) pairs (Q, 2)) that the next step will use.
      .def("neighbor_pairs_in_use", [](PyFluid& f) {
        std::vector<Index> pairs, boundary_pairs;
        {
          ReleaseGil release;
          pairs = f.solver->neighbor_pairs_in_use(f.state, boundary_pairs);
        }
        const Index p = static_cast<Index>(pairs.size()) / 2, q = static_cast<Index>(boundary_pairs.size()) / 2;
        return py::make_tuple(to_numpy(std::move(pairs), {p, 2}), to_numpy(std::move(boundary_pairs), {q, 2}));
      })
      .def_property_readonly("x", [](py::object self) {
        auto& f = self.cast<PyFluid&>();
        return view(self, f.state.x, {f.state.n, f.state.dim});
      })
      .def_property_readonly("v", [](py::object self) {
        auto& f = self.cast<PyFluid&>();
        return view(self, f.state.v, {f.state.n, f.state.dim});
      })
      .def_property_readonly("density", [](py::object self) {
        auto& f = self.cast<PyFluid&>();
        return view(self, f.state.density, {f.state.n});
      })
      .def_property_readonly("pressure", [](py::object self) {
        auto& f = self.cast<PyFluid&>();
        return view(self, f.state.pressure, {f.state.n});
      })
      .def_property_readonly("ids", [](py::object self) {
        auto& f = self.cast<PyFluid&>();
        return view(self, f.state.ids, {f.state.n});
      })
      .def_property("time", [](const PyFluid& f) { return f.state.time; },
                    [](PyFluid& f, Scalar t) { f.state.time = t; })
      // Settable for checkpoints: the Morton reordering is scheduled by the step count.
      .def_property("steps", [](const PyFluid& f) { return f.state.steps; },
                    [](PyFluid& f, Index n) { f.state.steps = n; })
      .def_property_readonly("mass", [](const PyFluid& f) { return f.solver->model().mass; })
      .def_property_readonly("support_radius", [](const PyFluid& f) { return f.solver->model().h; })
      .def_property_readonly("speed_of_sound", [](const PyFluid& f) { return f.solver->speed_of_sound(); })
      .def_property_readonly("boundary_count", [](const PyFluid& f) { return f.solver->model().boundary_count(); })
      .def_property_readonly("boundary_psi", [](const PyFluid& f) {
        auto psi = f.solver->model().boundary_psi;
        const Index m = static_cast<Index>(psi.size());
        return to_numpy(std::move(psi), {m});
      });

  m.def("neighbor_pairs", [](py::array points, Scalar radius) {
    const int d = dim_of(points, "points");
    const Index n = points.shape(0);
    const Scalar* x = checked_data(points, "points", n * d, false);
    std::vector<Index> pairs;
    {
      ReleaseGil release;
      pairs = d == 2 ? neighbor_pairs<2>(x, n, radius) : neighbor_pairs<3>(x, n, radius);
    }
    const Index count = static_cast<Index>(pairs.size()) / 2;
    return to_numpy(std::move(pairs), {count, 2});
  }, py::arg("points"), py::arg("radius"));

  m.def("kernel", [](py::array r, Scalar h, int d, int derivative) {
    const Scalar* rp = checked_data(r, "r", r.size(), false);
    std::vector<Scalar> out(static_cast<size_t>(r.size()));
    for (Index k = 0; k < r.size(); ++k)
      out[k] = derivative == 0 ? sph::kernel_w(rp[k], h, d)
             : derivative == 1 ? sph::kernel_dw(rp[k], h, d) : sph::kernel_d2w(rp[k], h, d);
    return to_numpy(std::move(out), shape_of(r));
  }, py::arg("r"), py::arg("h"), py::arg("d"), py::arg("derivative"));

  m.def("block", [](std::vector<Scalar> lower, std::vector<Scalar> upper, Scalar spacing) {
    const int d = static_cast<int>(lower.size());
    auto x = sph::block(d, lower.data(), upper.data(), spacing);
    const Index n = static_cast<Index>(x.size()) / d;
    return to_numpy(std::move(x), {n, d});
  }, py::arg("lower"), py::arg("upper"), py::arg("spacing"));

  m.def("box_boundary", [](std::vector<Scalar> lower, std::vector<Scalar> upper, Scalar spacing, int layers) {
    const int d = static_cast<int>(lower.size());
    auto x = sph::box_boundary(d, lower.data(), upper.data(), spacing, layers);
    const Index n = static_cast<Index>(x.size()) / d;
    return to_numpy(std::move(x), {n, d});
  }, py::arg("lower"), py::arg("upper"), py::arg("spacing"), py::arg("layers"));
}

}  // namespace kinema::bind
