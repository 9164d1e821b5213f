// kinema._core.massspring: the mass-spring Config, StepStats and enums as Python objects, and
// System, the holder of one Model, its State and Solver. The Python layer
// (kinema/massspring.py) broadcasts per-item parameters and converts shapes; values are checked
// in C++. x and v are zero-copy views of the State's own buffers, kept alive by the System.
#include <memory>
#include <string>

#include "bindings/common.h"
#include "core/errors.h"
#include "massspring/solver.h"

namespace kinema::bind {

namespace {

using namespace massspring;

struct System {
  Model model;
  State state;
  std::unique_ptr<Solver> solver;
  // step_adjoint's inputs and outputs, kept so that a backward pass reuses their buffers.
  State before, after, adjoint;
  Params params;
  // The states of the last Trajectory let go, whose buffers the next record reuses (a run's
  // states are tens of megabytes; fresh ones would page-fault in on every rollout).
  std::vector<State> spare;
};

// A run stored for reverse mode in C++ (System.record): the states before and after every step.
struct Trajectory {
  py::object owner;  // the System, kept alive
  System* system;
  Scalar dt;
  std::vector<State> states;
  bool controlled;
  ~Trajectory() {
    if (system && states.size() > system->spare.size()) system->spare = std::move(states);
  }
};

py::array view(py::object self, std::vector<Scalar>& buffer, Index d) {
  const Index rows = static_cast<Index>(buffer.size()) / d;
  return py::array_t<Scalar>({rows, d}, buffer.data(), self);
}

py::array copy_of(const std::vector<Scalar>& a, Index d) {
  return to_numpy(std::vector<Scalar>(a), {static_cast<Index>(a.size()) / d, d});
}

template <class T>
T item(const py::dict& s, const char* key) {
  if (!s.contains(key)) throw InvalidArgument(std::string("state: missing key '") + key + "'");
  return s[key].cast<T>();
}

// Copies an (n, d) float64 array out of a state dict into a buffer of the given size.
void read_array(const py::dict& s, const char* key, std::vector<Scalar>& out, Index size, int d,
                bool allow_empty = false) {
  if (!s.contains(key)) throw InvalidArgument(std::string("state: missing key '") + key + "'");
  const auto a = py::array_t<Scalar, py::array::c_style | py::array::forcecast>::ensure(s[key]);
  if (!a) throw InvalidArgument(std::string("state[") + key + "]: expected a float array");
  if (allow_empty && a.size() == 0) {
    out.clear();
    return;
  }
  if (a.size() != size)
    throw InvalidArgument(std::string("state[") + key + "]: expected shape (" +
                          std::to_string(size / d) + ", " + std::to_string(d) + "), got " +
                          std::to_string(a.size()) + " values");
  out.resize(size);  // same size: the buffer (and its numpy views) stays
  std::copy(a.data(), a.data() + size, out.begin());
}

py::dict to_dict(const State& s, Index d) {
  py::dict out;
  out["x"] = copy_of(s.x, d);
  out["v"] = copy_of(s.v, d);
  out["time"] = py::float_(s.time);
  out["step"] = py::int_(s.step);
  out["clamped"] = py::bool_(s.clamped);
  out["factor_valid"] = py::bool_(s.factor.valid);
  out["factor_refactor_next"] = py::bool_(s.factor.refactor_next);
  out["factor_clamped"] = py::bool_(s.factor.clamped);
  out["factor_dt"] = py::float_(s.factor.dt);
  out["factor_beta"] = py::float_(s.factor.beta);
  out["factor_x"] = copy_of(s.factor.x, d);
  return out;
}

// Reads a state() dict into s; with `checked`, into a copy first so that s is left as it was
// when the dict is refused (the simulation's own State).
void from_dict(const py::dict& in, State& s, Index n, int d, bool checked = true) {
  State staged;
  State& t = checked ? staged : s;
  read_array(in, "x", t.x, n, d);
  read_array(in, "v", t.v, n, d);
  read_array(in, "factor_x", t.factor.x, n, d, true);
  t.time = item<Scalar>(in, "time");
  t.step = item<Index>(in, "step");
  t.clamped = item<bool>(in, "clamped");
  t.factor.valid = item<bool>(in, "factor_valid");
  t.factor.refactor_next = item<bool>(in, "factor_refactor_next");
  t.factor.clamped = item<bool>(in, "factor_clamped");
  t.factor.dt = item<Scalar>(in, "factor_dt");
  t.factor.beta = item<Scalar>(in, "factor_beta");
  if (t.factor.valid && t.factor.x.empty())
    throw InvalidArgument("state[factor_x]: expected shape (n, d) when factor_valid");
  if (checked) s = t;  // copy assignment: x and v keep their buffers, so numpy views stay valid
}

std::vector<Scalar>& parameter(Model& m, const std::string& name) {
  if (name == "stiffness") return m.stiffness;
  if (name == "rest_length") return m.rest_length;
  if (name == "damping") return m.damping;
  if (name == "mass") return m.mass;
  throw InvalidArgument("name: expected 'stiffness', 'rest_length', 'damping' or 'mass', got '" +
                        name + "'");
}

const Scalar* optional_control(const py::object& control, Index size, std::vector<Scalar>& buffer) {
  if (control.is_none()) return nullptr;
  const auto a = py::array_t<Scalar, py::array::c_style | py::array::forcecast>::ensure(control);
  if (!a || a.size() != size)
    throw InvalidArgument("control: expected an (n, d) float array of " + std::to_string(size) +
                          " values");
  buffer.assign(a.data(), a.data() + size);
  for (Scalar u : buffer)
    if (!std::isfinite(u)) throw InvalidArgument("control: expected finite forces");
  return buffer.data();
}

}  // namespace

void bind_massspring(py::module_& m) {
  py::enum_<Integrator>(m, "Integrator")
      .value("explicit", Integrator::Explicit)
      .value("symplectic", Integrator::Symplectic)
      .value("implicit", Integrator::Implicit);

  py::class_<Config>(m, "Config", "Options of a mass-spring step (solver.h).")
      .def(py::init<>())
      .def_readwrite("integrator", &Config::integrator)
      .def_readwrite("beta", &Config::beta, "implicit weight: 1 backward Euler, 0.5 trapezoid-like")
      .def_readwrite("linear_solver", &Config::linear_solver)
      .def_readwrite("cg_tol", &Config::cg_tol, "relative residual of the (P)CG solves")
      .def_readwrite("adjoint_tol", &Config::adjoint_tol,
                     "relative residual of the adjoint's implicit solve (0: a direct solve)");

  m.def("check_config", &check_config, py::arg("config"),
        "Raises ValueError naming the first field out of range.");

  py::class_<StepStats, StepStatsBase>(m, "StepStats", "Statistics of System.step (summed over steps).")
      .def_readonly("clamped", &StepStats::clamped,
                    "the exact spring Jacobian was not positive definite and was clamped")
      .def_readonly("refactored", &StepStats::refactored, "a CHOLMOD factorisation was computed")
      .def_readonly("factorizations", &StepStats::factorizations)
      .def_readonly("cg_iterations", &StepStats::cg_iterations, "(P)CG iterations")
      .def_readonly("seconds_assembly", &StepStats::seconds_assembly)
      .def_readonly("seconds_factor", &StepStats::seconds_factor)
      .def_readonly("seconds_solve", &StepStats::seconds_solve)
      .def("__repr__", [](const StepStats& s) {
        return "StepStats(time=" + format_real(s.time) + ", dt=" + format_real(s.dt) +
               ", clamped=" + (s.clamped ? "True" : "False") +
               ", factorizations=" + std::to_string(s.factorizations) +
               ", cg_iterations=" + std::to_string(s.cg_iterations) +
               ", seconds=" + format_real(s.seconds) + ")";
      });

  py::class_<Trajectory>(m, "Trajectory", "A run System.record stored for reverse mode.")
      .def_property_readonly("steps", [](const Trajectory& t) {
        return static_cast<Index>(t.states.size()) - 1;
      })
      .def("backward",
           [](Trajectory& t, const py::object& grad_x, const py::object& grad_v, bool with_params) {
             System& s = *t.system;
             const Index n = s.model.vertex_count * s.model.dim;
             const int d = s.model.dim;
             const Index steps = static_cast<Index>(t.states.size()) - 1;
             py::dict grads;
             grads["x"] = grad_x;
             grads["v"] = grad_v;
             State adjoint;
             read_array(grads, "x", adjoint.x, n, d);
             read_array(grads, "v", adjoint.v, n, d);
             Params p;
             if (with_params) {
               p.stiffness.assign(s.model.spring_count, 0);
               p.rest_length.assign(s.model.spring_count, 0);
               p.damping.assign(s.model.spring_count, 0);
               p.mass.assign(s.model.vertex_count, 0);
             }
             std::vector<Scalar> gu(t.controlled ? steps * n : 0);
             Interrupt interrupt = python_interrupt();
             {
               ReleaseGil release;
               s.solver->run_adjoint(t.states, t.dt, adjoint, p, t.controlled ? gu.data() : nullptr,
                                     interrupt);
             }
             py::object params = py::none();
             if (with_params) {
               py::dict out;
               out["stiffness"] = to_numpy(std::move(p.stiffness), {s.model.spring_count});
               out["rest_length"] = to_numpy(std::move(p.rest_length), {s.model.spring_count});
               out["damping"] = to_numpy(std::move(p.damping), {s.model.spring_count});
               out["mass"] = to_numpy(std::move(p.mass), {s.model.vertex_count});
               params = out;
             }
             py::object gcontrols = py::none();
             if (t.controlled) gcontrols = to_numpy(std::move(gu), {steps, s.model.vertex_count, d});
             return py::make_tuple(to_numpy(std::move(adjoint.x), {s.model.vertex_count, d}),
                                   to_numpy(std::move(adjoint.v), {s.model.vertex_count, d}),
                                   params, gcontrols);
           },
           py::arg("grad_x"), py::arg("grad_v"), py::arg("with_params"),
           "dL/dx_0, dL/dv_0, the parameters' gradients summed over the steps (per item; None "
           "unless with_params) and dL/d(controls) (None without controls) from dL/dx_T, dL/dv_T.");

  py::class_<System>(m, "System")
      .def(py::init([](const ScalarArray& x, const IndexArray& springs, const ScalarArray& stiffness,
                       const ScalarArray& rest_length, const ScalarArray& damping,
                       const ScalarArray& mass, const IndexArray& fixed,
                       std::vector<Scalar> gravity) {
             if (x.ndim() != 2) throw InvalidArgument("x: expected shape (n, d)");
             if (springs.ndim() != 2 || springs.shape(1) != 2)
               throw InvalidArgument("springs: expected shape (m, 2)");
             const Index n = x.shape(0), count = springs.shape(0);
             if (stiffness.size() != count || rest_length.size() != count ||
                 damping.size() != count)
               throw InvalidArgument("stiffness, rest_length, damping: expected one per spring");
             if (mass.size() != n) throw InvalidArgument("mass: expected one per vertex");
             const int d = static_cast<int>(x.shape(1));
             ReleaseGil release;
             auto s = std::make_unique<System>();
             s->model = make_model(d, n, springs.data(), count, stiffness.data(),
                                   rest_length.data(), damping.data(), mass.data(), fixed.data(),
                                   fixed.size(), gravity);
             s->solver = std::make_unique<Solver>(s->model, Config{});
             s->state = s->solver->initial_state(x.data());
             return s;
           }),
           py::arg("x"), py::arg("springs"), py::arg("stiffness"), py::arg("rest_length"),
           py::arg("damping"), py::arg("mass"), py::arg("fixed"), py::arg("gravity"))
      .def_property_readonly("x", [](py::object self) {
        System& s = self.cast<System&>();
        return view(self, s.state.x, s.model.dim);
      })
      .def_property_readonly("v", [](py::object self) {
        System& s = self.cast<System&>();
        return view(self, s.state.v, s.model.dim);
      })
      .def_property_readonly("config", [](System& s) -> Config& { return s.solver->config(); },
                             py::return_value_policy::reference_internal)
      // Settable for checkpoints (km.Scene resumes a run bit for bit).
      .def_property("time", [](System& s) { return s.state.time; },
                    [](System& s, Scalar t) { s.state.time = t; })
      .def_property("step_count", [](System& s) { return s.state.step; },
                    [](System& s, Index n) { s.state.step = n; })
      // The explicit steps' stability bounds (massspring::ExplicitLimits), cached in C++ until a
      // parameter changes: each step's check reads them.
      .def_property_readonly("explicit_dt_limit", [](System& s) { return s.solver->explicit_limits().dt_limit; })
      .def_property_readonly("unstable_dt", [](System& s) { return s.solver->explicit_limits().unstable_dt; })
      .def_property_readonly("gershgorin_omega2", [](System& s) { return s.solver->explicit_limits().omega2; })
      .def("state", [](System& s) { return to_dict(s.state, s.model.dim); })
      .def("set_state", [](System& s, const py::dict& state) {
        from_dict(state, s.state, s.model.vertex_count * s.model.dim, s.model.dim);
      })
      .def("parameter", [](System& s, const std::string& name) {
        return to_numpy(std::vector<Scalar>(parameter(s.model, name)),
                        {static_cast<Index>(parameter(s.model, name).size())});
      })
      .def("set_parameter", [](System& s, const std::string& name, const ScalarArray& value) {
        std::vector<Scalar>& p = parameter(s.model, name);
        if (value.size() != static_cast<Index>(p.size()))
          throw InvalidArgument(name + ": expected " + std::to_string(p.size()) + " values, got " +
                                std::to_string(value.size()));
        const std::vector<Scalar> old = p;
        p.assign(value.data(), value.data() + value.size());
        try {
          check_parameters(s.model);
        } catch (...) {
          p = old;
          throw;
        }
        s.solver->model_changed();
      })
      .def("step",
           [](System& s, Scalar dt, Index steps, const py::object& control) {
             std::vector<Scalar> buffer;
             const Scalar* u = optional_control(control, s.model.vertex_count * s.model.dim, buffer);
             Interrupt interrupt = python_interrupt();
             StepStats stats, last;
             {
               ReleaseGil release;
               for (Index k = 0; k < steps; ++k) {
                 interrupt.check();
                 last = with_rollback(s.state, [&] { return s.solver->step(s.state, dt, interrupt, u); });
                 stats.clamped = stats.clamped || last.clamped;
                 stats.refactored = stats.refactored || last.refactored;
                 stats.cg_iterations += last.cg_iterations;
                 stats.factorizations += last.factorizations;
                 stats.seconds_assembly += last.seconds_assembly;
                 stats.seconds_factor += last.seconds_factor;
                 stats.seconds_solve += last.seconds_solve;
                 stats.seconds += last.seconds;
                 stats.time = last.time;
                 stats.dt = last.dt;
               }
             }
             return stats;
           },
           py::arg("dt"), py::arg("steps") = 1, py::arg("control") = py::none())
      .def("record",
           [](py::object self, Scalar dt, Index steps, const py::object& controls) {
             System& s = self.cast<System&>();
             const Index n = s.model.vertex_count * s.model.dim;
             std::vector<Scalar> forces;
             if (!controls.is_none()) {
               const auto a =
                   py::array_t<Scalar, py::array::c_style | py::array::forcecast>::ensure(controls);
               if (!a || a.size() != steps * n)
                 throw InvalidArgument("controls: expected a (steps, n, d) float array of " +
                                       std::to_string(steps * n) + " values");
               forces.assign(a.data(), a.data() + a.size());
               for (Scalar u : forces)
                 if (!std::isfinite(u)) throw InvalidArgument("controls: expected finite forces");
             }
             auto t = std::make_unique<Trajectory>();
             t->owner = self;
             t->system = &s;
             t->dt = dt;
             t->controlled = !forces.empty();
             Interrupt interrupt = python_interrupt();
             // What step_adjoint reads of a state, into the buffers of a spare state when there
             // is one; the lagged factor's record is not kept (it would add a third array to
             // every state held).
             std::vector<State> spare = std::move(s.spare);
             s.spare.clear();
             const auto kept = [&spare](const State& from) {
               State to;
               if (!spare.empty()) {
                 to = std::move(spare.back());
                 spare.pop_back();
               }
               to.x = from.x;  // copy assignment: reuses the spare's buffer
               to.v = from.v;
               to.time = from.time;
               to.step = from.step;
               to.clamped = from.clamped;
               return to;
             };
             const auto restore = [&s](const State& last, const FactorRecord& factor) {
               s.state.x = last.x;
               s.state.v = last.v;
               s.state.time = last.time;
               s.state.step = last.step;
               s.state.clamped = last.clamped;
               s.state.factor = factor;
             };
             {
               ReleaseGil release;
               t->states.reserve(static_cast<std::size_t>(steps) + 1);
               t->states.push_back(kept(s.state));
               if (s.solver->config().integrator != Integrator::Implicit) {
                 // Each step straight from the state before it into the next one kept (no
                 // copies); the System's state takes the last (or, on a failed step, the one
                 // before it).
                 for (Index k = 0; k < steps; ++k) {
                   interrupt.check();
                   const Scalar* u = forces.empty() ? nullptr : forces.data() + k * n;
                   State next;
                   if (!spare.empty()) {
                     next = std::move(spare.back());
                     spare.pop_back();
                   }
                   try {
                     s.solver->step(t->states.back(), next, dt, interrupt, u);
                   } catch (...) {
                     restore(t->states.back(), s.state.factor);
                     throw;
                   }
                   t->states.push_back(std::move(next));
                 }
                 restore(t->states.back(), s.state.factor);
                 return t;
               }
               for (Index k = 0; k < steps; ++k) {
                 interrupt.check();
                 const Scalar* u = forces.empty() ? nullptr : forces.data() + k * n;
                 // The rollback copy is the state just kept plus the factor's record (with_rollback
                 // without a third copy of x and v per step).
                 const FactorRecord factor = s.state.factor;
                 try {
                   s.solver->step(s.state, dt, interrupt, u);
                 } catch (...) {
                   restore(t->states.back(), factor);
                   throw;
                 }
                 t->states.push_back(kept(s.state));
               }
             }
             return t;
           },
           py::arg("dt"), py::arg("steps"), py::arg("controls") = py::none(),
           "Takes `steps` steps of dt (controls: None or (steps, n, d) forces) and returns the "
           "Trajectory of every state, for Trajectory.backward.")
      .def("step_adjoint",
           [](System& s, Scalar dt, const py::dict& before, const py::dict& after,
              const py::object& control, const py::object& grad_x, const py::object& grad_v) {
             const Index n = s.model.vertex_count * s.model.dim;
             const int d = s.model.dim;
             from_dict(before, s.before, n, d, false);
             from_dict(after, s.after, n, d, false);
             py::dict grads;
             grads["x"] = grad_x;
             grads["v"] = grad_v;
             read_array(grads, "x", s.adjoint.x, n, d);
             read_array(grads, "v", s.adjoint.v, n, d);
             std::vector<Scalar> buffer;
             const Scalar* u = optional_control(control, n, buffer);
             Params& p = s.params;
             p.stiffness.assign(s.model.spring_count, 0);
             p.rest_length.assign(s.model.spring_count, 0);
             p.damping.assign(s.model.spring_count, 0);
             p.mass.assign(s.model.vertex_count, 0);
             std::vector<Scalar> gu(u ? n : 0);
             Interrupt interrupt = python_interrupt();
             {
               ReleaseGil release;
               s.solver->step_adjoint(s.before, s.after, dt, s.adjoint, p, u ? gu.data() : nullptr, interrupt);
             }
             const auto copy = [](const std::vector<Scalar>& a, std::vector<Index> shape) {
               return to_numpy(std::vector<Scalar>(a), shape);
             };
             py::dict params;
             params["stiffness"] = copy(p.stiffness, {s.model.spring_count});
             params["rest_length"] = copy(p.rest_length, {s.model.spring_count});
             params["damping"] = copy(p.damping, {s.model.spring_count});
             params["mass"] = copy(p.mass, {s.model.vertex_count});
             py::object gcontrol = py::none();
             if (u) gcontrol = to_numpy(std::move(gu), {s.model.vertex_count, d});
             return py::make_tuple(copy(s.adjoint.x, {s.model.vertex_count, d}),
                                   copy(s.adjoint.v, {s.model.vertex_count, d}), params, gcontrol);
           },
           py::arg("dt"), py::arg("before"), py::arg("after"), py::arg("control"),
           py::arg("grad_x"), py::arg("grad_v"))
      .def("kinetic_energy", [](System& s) { return s.solver->kinetic_energy(s.state); })
      .def("spring_energy", [](System& s) { return s.solver->spring_energy(s.state); })
      .def("gravity_energy", [](System& s) { return s.solver->gravity_energy(s.state); })
      .def("forces", [](System& s) {
        std::vector<Scalar> f(s.state.x.size());
        s.solver->forces(s.state, f.data());
        const Index d = s.model.dim;
        const Index n = static_cast<Index>(f.size()) / d;
        return to_numpy(std::move(f), {n, d});
      });
}

}  // namespace kinema::bind
