// kinema._core.sph: the SPH fluid behind km.sph.Fluid (its Config, StepStats and Method bound as
// Python objects), the neighbour search and scene helpers. State arrays are zero-copy views of
// the C++ State whose base is the Fluid object; a step never reallocates them (Morton
// reordering permutes their rows in place); set_state copies into them.
#include <cmath>
#include <optional>
#include <type_traits>

#include "bindings/common.h"
#include "core/advance.h"
#include "core/errors.h"
#include "particles/neighbor_grid.h"
#include "sph/adjoint.h"
#include "sph/kernels.h"
#include "sph/solver.h"

namespace kinema::bind {

namespace {

int dim_of(const py::array& a, const char* name) {
  if (a.ndim() != 2 || (a.shape(1) != 2 && a.shape(1) != 3))
    throw InvalidArgument(std::string(name) + ": expected shape (n, 2) or (n, 3)");
  return static_cast<int>(a.shape(1));
}

// Copies the array src[key] of to.size() values into `to` (a ValueError naming the entry if it
// has another size).
template <class T>
void copy_into(std::vector<T>& to, const py::dict& src, const char* key) {
  const auto a = py::array_t<T, py::array::c_style | py::array::forcecast>::ensure(src[key]);
  const std::string name = std::string("state['") + key + "']";
  if (!a || a.size() != static_cast<py::ssize_t>(to.size()))
    throw InvalidArgument(name + ": expected " + std::to_string(to.size()) + " numbers");
  if constexpr (std::is_floating_point_v<T>)
    for (py::ssize_t k = 0; k < a.size(); ++k)
      if (!std::isfinite(a.data()[k])) throw InvalidArgument(name + ": expected finite values");
  std::copy(a.data(), a.data() + a.size(), to.begin());
}

struct PyFluid {
  PyFluid(py::array positions, py::array velocity, Scalar spacing, const sph::Config& config,
          std::optional<py::array> boundary, std::optional<std::vector<Scalar>> lower,
          std::optional<std::vector<Scalar>> upper)
      : state(dim_of(positions, "positions"), positions.shape(0)) {
    const int d = state.dim;
    const Scalar* xp = checked_data(positions, "positions", state.n * d, false);
    const Scalar* vp = checked_data(velocity, "velocity", state.n * d, false);
    std::copy(xp, xp + state.n * d, state.x.begin());
    std::copy(vp, vp + state.n * d, state.v.begin());
    std::vector<Scalar> xb;
    if (boundary) {
      if (boundary->ndim() != 2 || boundary->shape(1) != d)
        throw InvalidArgument("boundary: expected shape (M, " + std::to_string(d) + ")");
      const Scalar* bp = checked_data(*boundary, "boundary", boundary->size(), false);
      xb.assign(bp, bp + boundary->size());
    }
    for (const auto* corner : {&lower, &upper})
      if (*corner && (*corner)->size() != static_cast<size_t>(d))
        throw InvalidArgument("domain: expected " + std::to_string(d) + " coordinates per corner");
    ReleaseGil release;
    const sph::Model model = sph::make_model(config, state, spacing, std::move(xb),
                                             lower ? lower->data() : nullptr, upper ? upper->data() : nullptr);
    solver.emplace(model, config);
  }

  // forces: None or (n, d) external forces [N] by particle id (km.diff's controls).
  sph::StepStats step(Scalar dt, py::object forces) {
    const Scalar* f = forces_of(forces);
    Interrupt interrupt = python_interrupt();
    ReleaseGil release;
    return step_or_rollback(dt, interrupt, f);
  }

  // One step; a failing step leaves the state as it was.
  sph::StepStats step_or_rollback(Scalar dt, Interrupt& interrupt, const Scalar* forces = nullptr) {
    check_ids();
    return with_rollback(state, backup, [&] { return solver->step(state, dt, interrupt, forces); });
  }

  const Scalar* forces_of(py::object forces) {
    if (forces.is_none()) return nullptr;
    py::array a = forces.cast<py::array>();
    const Index n = state.n, d = state.dim;
    if (a.ndim() != 2 || a.shape(0) != n || a.shape(1) != d)
      throw InvalidArgument("controls: expected one step's forces of shape (" + std::to_string(n) + ", " +
                            std::to_string(d) + ") [N]");
    const Scalar* f = checked_data(a, "controls", n * d, false);
    forces_copy.assign(f, f + n * d);  // the array may be a temporary of the conversion
    return forces_copy.data();
  }

  // The rows of state()'s dict `src` (x, v, ids) as a State (named `name` in errors).
  sph::State state_from(const py::dict& src, const char* name) const {
    sph::State s(state.dim, state.n);
    for (const char* key : {"x", "v", "ids"})
      if (!src.contains(key)) throw InvalidArgument(std::string(name) + ": missing '" + key + "'");
    copy_into(s.x, src, "x");
    copy_into(s.v, src, "v");
    copy_into(s.ids, src, "ids");
    return s;
  }

  // The vector-Jacobian product of one step (Solver::step_adjoint): `before`/`after` are state()
  // dicts around step(dt, forces); grad_x, grad_v are dL/d(after). Returns (dL/dx, dL/dv of
  // before, dL/dnu, dL/dforces (n, d) by particle id or None when with_forces is false).
  py::tuple step_adjoint(Scalar dt, const py::dict& before_dict, const py::dict& after_dict, py::array grad_x,
                         py::array grad_v, bool with_forces) {
    const sph::State before = state_from(before_dict, "before");
    const sph::State after = state_from(after_dict, "after");
    const Index n = state.n, d = state.dim;
    sph::State adjoint(state.dim, state.n);
    const Scalar* gx = checked_data(grad_x, "grads['x']", n * d, false);
    const Scalar* gv = checked_data(grad_v, "grads['v']", n * d, false);
    adjoint.x.assign(gx, gx + n * d);
    adjoint.v.assign(gv, gv + n * d);
    sph::ParamsAdjoint params;
    std::vector<Scalar> forces_bar(with_forces ? static_cast<size_t>(n * d) : 0);
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      solver->step_adjoint(before, after, dt, adjoint, params, with_forces ? forces_bar.data() : nullptr, interrupt);
    }
    py::object fb = py::none();
    if (with_forces) fb = to_numpy(std::move(forces_bar), {n, d});
    return py::make_tuple(to_numpy(std::move(adjoint.x), {n, d}), to_numpy(std::move(adjoint.v), {n, d}),
                          params.viscosity, fb);
  }

  // A new kinematic viscosity nu [m^2/s] (checked as the Config is); the state is kept.
  void set_viscosity(Scalar nu) {
    sph::Config config = solver->config();
    config.viscosity = nu;
    solver = sph::Solver(solver->model(), config);  // built before the old one goes: a refused nu changes nothing
  }

  // Steps of CFL-limited dt until `duration` has passed; Ctrl-C is checked between steps.
  py::tuple advance(Scalar duration, Scalar cfl) {
    sph::StepStats last;
    AdvanceResult result;
    Index unconverged = 0;  // DFSPH steps whose density or divergence solve stopped at max_iter
    Scalar worst = 0;       // their largest density error
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      result = advance_to(
          state, duration, [&](const sph::State& s) { return solver->stable_dt(s, cfl); },
          [&](sph::State&, Scalar dt) { return step_or_rollback(dt, interrupt); },
          [&](const sph::StepStats& stats) {
            last = stats;
            if (!stats.density_converged || !stats.divergence_converged) {
              ++unconverged;
              worst = std::max(worst, stats.density_error);
            }
          },
          interrupt);
    }
    return py::make_tuple(result.steps, last, unconverged, worst);
  }

  // The ids view is writable (checkpoints restore it), so a step first checks that it still
  // is a permutation of 0..n-1: the ids label the particles the step moves and reorders.
  void check_ids() {
    std::vector<char>& seen = ids_seen;
    seen.assign(static_cast<size_t>(state.n), 0);
    for (Index k = 0; k < state.n; ++k) {
      const Index id = state.ids[k];
      if (id < 0 || id >= state.n || seen[id])
        throw InvalidArgument("ids: row " + std::to_string(k) + " holds " + std::to_string(id) +
                              ", which is out of range or repeated; ids must be a permutation of 0.." +
                              std::to_string(state.n - 1));
      seen[id] = 1;
    }
  }

  // Copies of everything the State holds, the neighbour lists as the positions and skin they
  // were built with (neighbor_x has 0 rows when there are none yet).
  py::dict get_state() const {
    const Index n = state.n, d = state.dim;
    py::dict out;
    out["x"] = to_numpy(std::vector<Scalar>(state.x), {n, d});
    out["v"] = to_numpy(std::vector<Scalar>(state.v), {n, d});
    out["density"] = to_numpy(std::vector<Scalar>(state.density), {n});
    out["pressure"] = to_numpy(std::vector<Scalar>(state.pressure), {n});
    out["ids"] = to_numpy(std::vector<Index>(state.ids), {n});
    out["time"] = py::array_t<Scalar>(std::vector<py::ssize_t>{}, &state.time);
    out["steps"] = py::array_t<Index>(std::vector<py::ssize_t>{}, &state.steps);
    out["last_dt"] = py::array_t<Scalar>(std::vector<py::ssize_t>{}, &state.last_dt);
    out["reorder_step"] = py::array_t<Index>(std::vector<py::ssize_t>{}, &state.reorder_step);
    if (solver->config().method == sph::Method::DFSPH) {
      // Empty until the first step sizes them: zero stiffnesses, as a cold start has.
      auto stiffness = [&](const std::vector<Scalar>& k) {
        return to_numpy(k.empty() ? std::vector<Scalar>(static_cast<size_t>(n), 0) : std::vector<Scalar>(k), {n});
      };
      out["kappa_density"] = stiffness(state.kappa_density);
      out["kappa_divergence"] = stiffness(state.kappa_divergence);
    }
    const bool lists = state.lists != nullptr;
    out["neighbor_x"] = to_numpy(lists ? std::vector<Scalar>(state.lists->x) : std::vector<Scalar>(), {lists ? n : 0, d});
    const Scalar skin = lists ? state.lists->skin : 0;
    out["neighbor_skin"] = py::array_t<Scalar>(std::vector<py::ssize_t>{}, &skin);
    return out;
  }

  // Restores get_state()'s dict (Python has checked its keys and converted its scalars); all
  // or nothing: the state changes only once every entry has been read and checked.
  void set_state(const py::dict& src, Scalar time, Index steps, Scalar last_dt, Index reorder_step,
                 Scalar neighbor_skin) {
    sph::State next = state;
    copy_into(next.x, src, "x");
    copy_into(next.v, src, "v");
    copy_into(next.density, src, "density");
    copy_into(next.pressure, src, "pressure");
    copy_into(next.ids, src, "ids");
    if (solver->config().method == sph::Method::DFSPH) {
      next.kappa_density.resize(static_cast<size_t>(state.n));
      next.kappa_divergence.resize(static_cast<size_t>(state.n));
      copy_into(next.kappa_density, src, "kappa_density");
      copy_into(next.kappa_divergence, src, "kappa_divergence");
    }
    if (!std::isfinite(time)) throw InvalidArgument("state['time']: expected a finite time [s]");
    if (steps < 0) throw InvalidArgument("state['steps']: expected an integer >= 0");
    if (!(last_dt >= 0) || !std::isfinite(last_dt)) throw InvalidArgument("state['last_dt']: expected a finite dt >= 0 [s]");
    if (reorder_step < -1 || reorder_step > steps)
      throw InvalidArgument("state['reorder_step']: expected an integer in [-1, steps]");
    next.time = time;
    next.steps = steps;
    next.last_dt = last_dt;
    next.reorder_step = reorder_step;
    const auto neighbor_x = py::array_t<Scalar, py::array::c_style | py::array::forcecast>::ensure(src["neighbor_x"]);
    if (!neighbor_x) throw InvalidArgument("state['neighbor_x']: expected an array of positions");
    ReleaseGil release;
    if (neighbor_x.size() == 0) {
      next.lists = nullptr;
    } else {
      const std::vector<Scalar> x(neighbor_x.data(), neighbor_x.data() + neighbor_x.size());
      solver->restore_lists(next, x, neighbor_skin);
    }
    state = next;
  }

  sph::State state;
  sph::State backup{2, 0};       // the state before the current step (step_or_rollback)
  std::vector<char> ids_seen;    // check_ids' scratch, kept so that a step allocates nothing
  std::vector<Scalar> forces_copy;  // the current step's forces
  std::optional<sph::Solver> solver;
};

// A view of one State buffer whose base is the Fluid object (kept alive by the array).
template <class T>
py::array view(py::object self, std::vector<T>& buffer, std::vector<py::ssize_t> shape) {
  return py::array_t<T>(shape, buffer.data(), self);
}

}  // namespace

void bind_sph(py::module_& m) {
  py::enum_<sph::Method>(m, "Method", "The pressure solver: WCSPH (Becker and Teschner 2007) or DFSPH "
                                      "(Bender and Koschier 2017).")
      .value("WCSPH", sph::Method::WCSPH)
      .value("DFSPH", sph::Method::DFSPH);
  m.def("parse_method", &sph::parse_method, py::arg("name"));

  using sph::Config;
  py::class_<Config>(m, "Config", "The parameters of an SPH liquid (checked when a Fluid is built).")
      .def(py::init<>())
      .def_readwrite("method", &Config::method)
      .def_readwrite("rho0", &Config::rho0, "rest density [kg/m^d]")
      .def_readwrite("viscosity", &Config::viscosity, "kinematic viscosity [m^2/s]; 0 skips the pass")
      .def_readwrite("gravity", &Config::gravity, "[m/s^2], the first d components are used")
      .def_readwrite("speed_of_sound", &Config::speed_of_sound,
                     "WCSPH c [m/s]; 0: 10 sqrt(2 |g| H) for the initial fluid height H")
      .def_readwrite("gamma", &Config::gamma, "Tait exponent")
      .def_readwrite("tol", &Config::tol, "DFSPH: mean relative compression after the density solve")
      .def_readwrite("divergence_tol", &Config::divergence_tol,
                     "DFSPH: mean (d rho/dt) dt / rho0 after the divergence solve")
      .def_readwrite("max_iter", &Config::max_iter, "DFSPH: iterations per solve")
      .def_readwrite("divergence_solve", &Config::divergence_solve, "DFSPH: run the divergence-free solver")
      .def_readwrite("reorder_every", &Config::reorder_every, "least steps between Morton reorderings (0: never)")
      .def_readwrite("neighbor_skin", &Config::neighbor_skin, "Verlet skin of the neighbour lists, fraction of h")
      .def_readwrite("warm_start", &Config::warm_start,
                     "DFSPH: share of the last step's stiffnesses a solve starts from")
      .def_readwrite("coarse_correction", &Config::coarse_correction,
                     "DFSPH: two-level density solve, a coarse correction in height (needs gravity): "
                     "1 on, 0 off, -1 on where tol > 1e-3")
      .def_readwrite("shepard_walls", &Config::shepard_walls,
                     "DFSPH: the domain's walls carry the Shepard average of their neighbours' stiffness");

  using sph::StepStats;
  py::class_<StepStats, StepStatsBase>(m, "StepStats", "What one SPH step did.")
      .def_readonly("iterations", &StepStats::iterations, "DFSPH constant-density iterations")
      .def_readonly("divergence_iterations", &StepStats::divergence_iterations, "DFSPH divergence-free iterations")
      .def_readonly("density_error", &StepStats::density_error,
                    "mean compression max(rho/rho0 - 1, 0) (DFSPH: what the density solve reached)")
      .def_readonly("divergence_error", &StepStats::divergence_error, "the divergence solve's error (DFSPH)")
      .def_readonly("density_converged", &StepStats::density_converged,
                    "DFSPH: the density solve ended within tol (False: stopped at max_iter)")
      .def_readonly("divergence_converged", &StepStats::divergence_converged,
                    "DFSPH: the divergence solve ended within divergence_tol (False: stopped at max_iter)")
      .def_readonly("max_speed", &StepStats::max_speed, "after the step [m/s]")
      .def_readonly("neighbor_count", &StepStats::neighbor_count, "fluid-fluid neighbour entries (2 per pair)")
      .def_readonly("neighbor_rebuild", &StepStats::neighbor_rebuild,
                    "the neighbour lists were rebuilt from the cell grid")
      .def_readonly("search_seconds", &StepStats::search_seconds,
                    "wall time of the neighbour search (grid, Verlet lists, reordering) [s]")
      .def_readonly("kernel_seconds", &StepStats::kernel_seconds,
                    "wall time of the kernel pass (densities, kernel gradients, DFSPH factors) [s]")
      .def_readonly("solve_seconds", &StepStats::solve_seconds,
                    "wall time of the pressure solves (DFSPH) or the pressure force (WCSPH) [s]")
      .def("__repr__", [](const StepStats& s) {
        return "sph.StepStats(time=" + format_real(s.time) + ", dt=" + format_real(s.dt) +
               ", iterations=" + std::to_string(s.iterations) + ", divergence_iterations=" +
               std::to_string(s.divergence_iterations) + ", density_error=" + format_real(s.density_error) +
               ", max_speed=" + format_real(s.max_speed) + ")";
      });

  py::class_<PyFluid>(m, "Fluid")
      .def(py::init<py::array, py::array, Scalar, const sph::Config&, std::optional<py::array>,
                    std::optional<std::vector<Scalar>>, std::optional<std::vector<Scalar>>>(),
           py::arg("positions"), py::arg("velocity"), py::arg("spacing"), py::arg("config"),
           py::arg("boundary"), py::arg("lower"), py::arg("upper"))
      .def("step", &PyFluid::step, py::arg("dt"), py::arg("forces") = py::none())
      .def("step_adjoint", &PyFluid::step_adjoint, py::arg("dt"), py::arg("before"), py::arg("after"),
           py::arg("grad_x"), py::arg("grad_v"), py::arg("with_forces"))
      .def("set_viscosity", &PyFluid::set_viscosity, py::arg("viscosity"))
      .def("advance", &PyFluid::advance, py::arg("duration"), py::arg("cfl"))
      .def("stable_dt", [](const PyFluid& f, Scalar cfl) { return f.solver->stable_dt(f.state, cfl); },
           py::arg("cfl"))
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
      .def("state", &PyFluid::get_state)
      .def("set_state", &PyFluid::set_state, py::arg("state"), py::arg("time"), py::arg("steps"),
           py::arg("last_dt"), py::arg("reorder_step"), py::arg("neighbor_skin"))
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
      .def_property_readonly("time", [](const PyFluid& f) { return f.state.time; })
      .def_property_readonly("steps", [](const PyFluid& f) { return f.state.steps; })
      .def_property_readonly("config", [](const PyFluid& f) { return f.solver->config(); })
      .def_property_readonly("mass", [](const PyFluid& f) { return f.solver->model().mass; })
      .def_property_readonly("support_radius", [](const PyFluid& f) { return f.solver->model().h; })
      .def_property_readonly("speed_of_sound", [](const PyFluid& f) { return f.solver->model().speed_of_sound; })
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
