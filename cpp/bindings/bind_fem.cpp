// kinema._core.fem: the finite-element body as Config / Parameters / Model / State / Solver
// (fem/model.h, fem/solver.h) and the pointwise material functions. The Python layer
// (kinema/fem.py) converts shapes and names; values are checked here, where they enter C++.
// State.x and State.v are zero-copy flat views of the state's own buffers, kept alive by the
// state (the buffers are never reallocated: steps and set_state copy into them).
#include <optional>
#include <string>
#include <type_traits>
#include <vector>

#include "bindings/common.h"
#include "bindings/fem_material.h"
#include "core/errors.h"
#include "core/parallel.h"
#include "fem/solver.h"

namespace kinema::bind {

namespace {

using fem::Solver;
using fem::State;

// A flat writable view of a state buffer owned by the state behind `self`.
py::array view(py::object self, std::vector<Scalar>& buffer) {
  return py::array_t<Scalar>(static_cast<py::ssize_t>(buffer.size()), buffer.data(), self);
}

// Copies a flat array of the buffer's size into it (in place: views stay valid).
void assign(std::vector<Scalar>& buffer, const ScalarArray& a, const char* name) {
  if (static_cast<std::size_t>(a.size()) != buffer.size())
    throw InvalidArgument(std::string(name) + ": expected " + std::to_string(buffer.size()) +
                          " values, got " + std::to_string(a.size()));
  std::copy(a.data(), a.data() + a.size(), buffer.begin());
}

// A control or gradient argument: None, or exactly the model's n d values.
const Scalar* optional_dofs(const std::optional<ScalarArray>& a, const fem::Model& m,
                            const char* name) {
  if (!a) return nullptr;
  const Index size = m.vertex_count * m.dim;
  if (a->size() != size)
    throw InvalidArgument(std::string(name) + ": expected shape (" +
                          std::to_string(m.vertex_count) + ", " + std::to_string(m.dim) +
                          "), got " + std::to_string(a->size()) + " values");
  return a->data();
}

// The parameter gradients named in `wanted` (None: all of them).
fem::ParameterMask parameter_mask(const std::optional<std::vector<std::string>>& wanted) {
  fem::ParameterMask mask;
  if (!wanted) return mask;
  mask = {false, false, false, false};
  for (const std::string& name : *wanted) {
    if (name == "youngs_modulus") mask.youngs_modulus = true;
    else if (name == "poisson_ratio") mask.poisson_ratio = true;
    else if (name == "density") mask.density = true;
    else if (name == "damping") mask.damping = true;
    else
      throw InvalidArgument("wanted: unknown parameter '" + name +
                            "' (expected youngs_modulus, poisson_ratio, density, damping)");
  }
  return mask;
}

// Applies a pointwise function to F of shape (k, D, D) (row-major, as numpy gives it).
template <int D, class Fn>
void pointwise(const Scalar* F, Index count, Scalar* out, Index out_size, Fn&& fn) {
  parallel_for(count, [&](Index k) {
    const Eigen::Map<const Eigen::Matrix<Scalar, D, D, Eigen::RowMajor>> Fr(F + k * D * D);
    fn(fem::Mat<D>(Fr), out + k * out_size);
  });
}

}  // namespace

void bind_fem(py::module_& m) {
  py::enum_<fem::Integrator>(m, "Integrator")
      .value("implicit", fem::Integrator::Implicit)
      .value("symplectic", fem::Integrator::Symplectic);
  py::enum_<fem::Definiteness>(m, "Definiteness")
      .value("adaptive", fem::Definiteness::Adaptive)
      .value("project", fem::Definiteness::Project)
      .value("none", fem::Definiteness::None);
  py::enum_<fem::Material>(m, "Material")
      .value("linear", fem::Material::Linear)
      .value("stvk", fem::Material::StVK)
      .value("corotated", fem::Material::Corotated)
      .value("neohookean", fem::Material::NeoHookean);

  py::class_<fem::Config>(m, "Config", "How a step is taken (fem/model.h).")
      .def(py::init<>())
      .def_readwrite("integrator", &fem::Config::integrator)
      .def_readwrite("tol", &fem::Config::tol, "Newton: ||grad g|| <= tol ||grad g(x0)||")
      .def_readwrite("max_newton", &fem::Config::max_newton)
      .def_readwrite("linear_solver", &fem::Config::linear_solver)
      .def_readwrite("cg_tol", &fem::Config::cg_tol)
      .def_readwrite("definiteness", &fem::Config::definiteness);

  py::class_<fem::Parameters>(m, "Parameters", "Material inputs of a Model.")
      .def(py::init<>())
      .def_readwrite("material", &fem::Parameters::material)
      .def_readwrite("youngs_modulus", &fem::Parameters::youngs_modulus, "[Pa], 1 or m values")
      .def_readwrite("poisson_ratio", &fem::Parameters::poisson_ratio, "1 or m values")
      .def_readwrite("density", &fem::Parameters::density, "[kg/m^d]")
      .def_readwrite("damping", &fem::Parameters::damping, "[1/s]")
      .def_readwrite("gravity", &fem::Parameters::gravity, "[m/s^2], empty or d values");

  py::class_<fem::Model>(m, "Model")
      .def(py::init([](const ScalarArray& vertices, const IndexArray& elements,
                       const fem::Parameters& parameters, const IndexArray& fixed) {
             if (vertices.ndim() != 2) throw InvalidArgument("vertices: expected shape (n, d)");
             const int d = static_cast<int>(vertices.shape(1));
             if (elements.ndim() != 2 || elements.shape(1) != d + 1)
               throw InvalidArgument("elements: expected shape (m, " + std::to_string(d + 1) + ")");
             ReleaseGil release;
             return fem::make_model(d, vertices.data(), vertices.shape(0), elements.data(),
                                    elements.shape(0), parameters, fixed.data(), fixed.size());
           }),
           py::arg("vertices"), py::arg("elements"), py::arg("parameters"), py::arg("fixed"))
      .def_readonly("dim", &fem::Model::dim)
      .def_readonly("vertex_count", &fem::Model::vertex_count)
      .def_readonly("element_count", &fem::Model::element_count)
      .def_readonly("fixed_count", &fem::Model::fixed_count)
      .def_readonly("parameters", &fem::Model::parameters)
      .def_property_readonly("rest", [](const fem::Model& b) {
        return py::array_t<Scalar>({b.vertex_count, static_cast<Index>(b.dim)}, b.rest.data());
      })
      .def_property_readonly("mass", [](const fem::Model& b) {
        return py::array_t<Scalar>(b.vertex_count, b.mass.data());
      })
      .def_property_readonly("volume", [](const fem::Model& b) {
        return py::array_t<Scalar>(b.element_count, b.volume.data());
      })
      .def_property_readonly("mu", [](const fem::Model& b) {
        return py::array_t<Scalar>(b.element_count, b.mu.data());
      })
      .def_property_readonly("lam", [](const fem::Model& b) {
        return py::array_t<Scalar>(b.element_count, b.lam.data());
      })
      .def("initial_state", &fem::initial_state);

  py::class_<State>(m, "State", "x, v: flat (n d) views [m], [m/s]; time [s]; step; the "
                                "record of the lagged CHOLMOD factor (fem/model.h).")
      .def(py::init<const State&>())
      .def_property("x", [](py::object self) { return view(self, self.cast<State&>().x); },
                    [](State& s, const ScalarArray& a) { assign(s.x, a, "x"); })
      .def_property("v", [](py::object self) { return view(self, self.cast<State&>().v); },
                    [](State& s, const ScalarArray& a) { assign(s.v, a, "v"); })
      .def_readwrite("time", &State::time)
      .def_readwrite("step", &State::step)
      .def_property("factor_x",
                    [](const State& s) {
                      return py::array_t<Scalar>(static_cast<py::ssize_t>(s.factor.x.size()),
                                                 s.factor.x.data());
                    },
                    [](State& s, const ScalarArray& a) {
                      if (a.size() != 0 && static_cast<std::size_t>(a.size()) != s.x.size())
                        throw InvalidArgument("factor_x: expected " + std::to_string(s.x.size()) +
                                              " values or none, got " + std::to_string(a.size()));
                      s.factor.x.assign(a.data(), a.data() + a.size());
                    })
      .def_property("factor_weight", [](const State& s) { return s.factor.weight; },
                    [](State& s, Scalar w) { s.factor.weight = w; })
      .def_property("factor_scale", [](const State& s) { return s.factor.scale; },
                    [](State& s, Scalar w) { s.factor.scale = w; })
      .def_property("factor_projected", [](const State& s) { return s.factor.projected; },
                    [](State& s, bool p) { s.factor.projected = p; })
      .def_property("refactor_pending", [](const State& s) { return s.factor.refactor_pending; },
                    [](State& s, bool p) { s.factor.refactor_pending = p; });

  py::class_<fem::StepStats, StepStatsBase>(m, "StepStats",
                                             "Statistics of one step or static solve.")
      .def_readonly("iterations", &fem::StepStats::iterations, "Newton iterations")
      .def_readonly("converged", &fem::StepStats::converged)
      .def_readonly("gradient_norm", &fem::StepStats::gradient_norm,
                    "||grad g|| at every iterate (absolute: [kg m] for a step, [N] static)")
      .def_readonly("step_length", &fem::StepStats::step_length,
                    "accepted line-search step of each iteration (1 = full Newton step)")
      .def_readonly("projected_elements", &fem::StepStats::projected_elements,
                    "elements whose dP/dF was clamped in the last iteration")
      .def_readonly("cg_iterations", &fem::StepStats::cg_iterations)
      .def_readonly("factorizations", &fem::StepStats::factorizations)
      .def_readonly("seconds_assembly", &fem::StepStats::seconds_assembly)
      .def_readonly("seconds_factor", &fem::StepStats::seconds_factor)
      .def_readonly("seconds_solve", &fem::StepStats::seconds_solve)
      .def_readonly("seconds_line_search", &fem::StepStats::seconds_line_search)
      .def_property_readonly("residual", [](const fem::StepStats& s) {
        const auto& g = s.gradient_norm;
        return !g.empty() && g[0] > 0 ? g.back() / g[0] : 0.0;
      }, "final relative gradient norm ||grad|| / ||grad_0||")
      .def("__repr__", [](const fem::StepStats& s) {
        return "StepStats(iterations=" + std::to_string(s.iterations) +
               ", converged=" + (s.converged ? "True" : "False") +
               ", factorizations=" + std::to_string(s.factorizations) +
               ", cg_iterations=" + std::to_string(s.cg_iterations) +
               ", seconds=" + format_real(s.seconds) + ")";
      });

  py::class_<fem::ParameterGradient>(m, "ParameterGradient")
      .def_property_readonly("youngs_modulus", [](const fem::ParameterGradient& g) {
        return py::array_t<Scalar>(static_cast<py::ssize_t>(g.youngs_modulus.size()),
                                   g.youngs_modulus.data());
      })
      .def_property_readonly("poisson_ratio", [](const fem::ParameterGradient& g) {
        return py::array_t<Scalar>(static_cast<py::ssize_t>(g.poisson_ratio.size()),
                                   g.poisson_ratio.data());
      })
      .def_readonly("density", &fem::ParameterGradient::density)
      .def_readonly("damping", &fem::ParameterGradient::damping);

  py::class_<fem::StoredRun>(m, "StoredRun", "A run Solver.record kept for run_adjoint.")
      .def_property_readonly("steps", &fem::StoredRun::steps)
      .def_property_readonly("distinct_factors", [](const fem::StoredRun& r) {
        return static_cast<Index>(r.factors.size());
      }, "factor records held (one per forward refactorisation, shared by the states between)");

  py::class_<Solver>(m, "Solver")
      .def(py::init([](const fem::Model& model, const fem::Config& config) {
             ReleaseGil release;
             return std::make_unique<Solver>(model, config);
           }),
           py::arg("model"), py::arg("config"), py::keep_alive<1, 2>())
      .def_property("config", [](Solver& s) { return s.config(); },
                    [](Solver& s, const fem::Config& c) { s.config() = c; })
      .def_property_readonly("explicit_dt_limit", &Solver::explicit_dt_limit)
      .def("step",
           [](Solver& s, State& state, Scalar dt, const std::optional<ScalarArray>& control) {
             const Scalar* u = optional_dofs(control, s.model(), "control");
             Interrupt interrupt = python_interrupt();
             ReleaseGil release;
             return with_rollback(state, [&] { return s.step(state, dt, interrupt, u); });
           },
           py::arg("state"), py::arg("dt"), py::arg("control") = py::none())
      .def("solve_static",
           [](Solver& s, State& state, Index load_steps) {
             Interrupt interrupt = python_interrupt();
             ReleaseGil release;
             return with_rollback(state, [&] { return s.solve_static(state, load_steps, interrupt); });
           },
           py::arg("state"), py::arg("load_steps"))
      .def("step_adjoint",
           [](Solver& s, const State& before, const State& after, Scalar dt,
              const std::optional<ScalarArray>& control, const ScalarArray& grad_x,
              const ScalarArray& grad_v, const std::optional<std::vector<std::string>>& wanted) {
             const fem::Model& md = s.model();
             const fem::ParameterMask mask = parameter_mask(wanted);
             const Scalar* u = optional_dofs(control, md, "control");
             State adjoint;
             adjoint.x.resize(md.rest.size());
             adjoint.v.resize(md.rest.size());
             assign(adjoint.x, grad_x, "grad x");
             assign(adjoint.v, grad_v, "grad v");
             std::vector<Scalar> grad_control(control ? md.rest.size() : 0);
             fem::ParameterGradient params;
             Interrupt interrupt = python_interrupt();
             {
               ReleaseGil release;
               s.step_adjoint(before, after, dt, u, adjoint, params,
                              control ? grad_control.data() : nullptr, interrupt, mask);
             }
             const Index n = md.vertex_count, d = md.dim;
             py::object gc = py::none();
             if (control) gc = to_numpy(std::move(grad_control), {n, d});
             return py::make_tuple(to_numpy(std::move(adjoint.x), {n, d}),
                                   to_numpy(std::move(adjoint.v), {n, d}), params, gc);
           },
           py::arg("before"), py::arg("after"), py::arg("dt"), py::arg("control"),
           py::arg("grad_x"), py::arg("grad_v"), py::arg("wanted") = py::none())
      .def("record",
           [](Solver& s, State& state, Scalar dt, Index steps,
              const std::optional<ScalarArray>& controls) {
             const Index size = s.model().vertex_count * s.model().dim;
             if (controls && controls->size() != steps * size)
               throw InvalidArgument("controls: expected " + std::to_string(steps) + " x " +
                                     std::to_string(size) + " values, got " +
                                     std::to_string(controls->size()));
             auto run = std::make_unique<fem::StoredRun>();
             Interrupt interrupt = python_interrupt();
             {
               ReleaseGil release;
               s.record(state, dt, steps, controls ? controls->data() : nullptr, *run, interrupt);
             }
             return run;
           },
           py::arg("state"), py::arg("dt"), py::arg("steps"), py::arg("controls") = py::none(),
           "Takes `steps` steps of dt from state (controls: None or (steps n d) forces) and "
           "returns the StoredRun of every state, for run_adjoint.")
      .def("run_adjoint",
           [](Solver& s, const fem::StoredRun& run, const std::optional<ScalarArray>& controls,
              const ScalarArray& grad_x, const ScalarArray& grad_v,
              const std::optional<std::vector<std::string>>& wanted) {
             const fem::Model& md = s.model();
             const fem::ParameterMask mask = parameter_mask(wanted);
             const Index size = md.vertex_count * md.dim, steps = run.steps();
             for (const State& st : run.states)
               if (static_cast<Index>(st.x.size()) != size)
                 throw InvalidArgument("run: a run of another body (expected states of " +
                                       std::to_string(md.vertex_count) + " vertices)");
             if (controls && controls->size() != steps * size)
               throw InvalidArgument("controls: expected " + std::to_string(steps) + " x " +
                                     std::to_string(size) + " values, got " +
                                     std::to_string(controls->size()));
             State adjoint;
             adjoint.x.resize(md.rest.size());
             adjoint.v.resize(md.rest.size());
             assign(adjoint.x, grad_x, "grad x");
             assign(adjoint.v, grad_v, "grad v");
             std::vector<Scalar> grad_controls(controls ? steps * size : 0);
             fem::ParameterGradient params;
             Interrupt interrupt = python_interrupt();
             {
               ReleaseGil release;
               s.run_adjoint(run, controls ? controls->data() : nullptr, adjoint, params,
                             controls ? grad_controls.data() : nullptr, interrupt, mask);
             }
             const Index n = md.vertex_count, d = md.dim;
             py::object gc = py::none();
             if (controls) gc = to_numpy(std::move(grad_controls), {steps, n, d});
             return py::make_tuple(to_numpy(std::move(adjoint.x), {n, d}),
                                   to_numpy(std::move(adjoint.v), {n, d}), params, gc);
           },
           py::arg("run"), py::arg("controls"), py::arg("grad_x"), py::arg("grad_v"),
           py::arg("wanted") = py::none(),
           "dL/d(first state) from dL/d(end state) over a StoredRun, last step first: "
           "(grad x, grad v, ParameterGradient summed over the steps, grad controls or None).")
      .def("elastic_energy", [](const Solver& s, const State& st) { return s.elastic_energy(st.x.data()); })
      .def("kinetic_energy", [](const Solver& s, const State& st) { return s.kinetic_energy(st.v.data()); })
      .def("gravity_energy", [](const Solver& s, const State& st) { return s.gravity_energy(st.x.data()); })
      .def("forces", [](Solver& s, const State& st) {
        std::vector<Scalar> f(st.x.size());
        {
          ReleaseGil release;
          s.forces(st.x.data(), f.data());
        }
        const Index d = s.model().dim;
        const Index n = static_cast<Index>(f.size()) / d;
        return to_numpy(std::move(f), {n, d});
      })
      .def("hessian", [](Solver& s, const State& st, bool project) {
        const ElementAssembly& p = s.pattern();
        std::vector<Scalar> values(p.nonzeros());
        {
          ReleaseGil release;
          s.projected_hessian(st.x.data(), project, values.data());
        }
        std::vector<Index> row_ptr = p.row_ptr(), col = p.col_index();
        const Index nnz = p.nonzeros();
        return py::make_tuple(to_numpy(std::move(row_ptr), {p.dof_count() + 1}),
                              to_numpy(std::move(col), {nnz}), to_numpy(std::move(values), {nnz}));
      }, py::arg("state"), py::arg("project"));

  // Pointwise material functions on F of shape (k, d, d): psi -> (k,), P -> (k, d, d),
  // dP/dF -> (k, d*d, d*d) on vec(F) column-major.
  m.def("lame", [](Scalar E, Scalar nu) {
    Scalar mu, lam;
    fem::lame(E, nu, mu, lam);
    return py::make_tuple(mu, lam);
  });
  m.def("pointwise", [](const ScalarArray& F, const std::string& what, const std::string& material,
                        Scalar mu, Scalar lam, bool project) {
    if (F.ndim() != 3 || F.shape(1) != F.shape(2) || (F.shape(1) != 2 && F.shape(1) != 3))
      throw InvalidArgument("F: expected shape (..., d, d) with d = 2 or 3");
    const fem::Material mat = parse_material(material);
    const int d = static_cast<int>(F.shape(1));
    const Index count = F.shape(0);
    const int kind = what == "psi" ? 0 : what == "piola" ? 1 : 2;
    const Index out_size = kind == 0 ? 1 : kind == 1 ? d * d : d * d * d * d;
    std::vector<Scalar> out(count * out_size);
    const Scalar* Fp = F.data();
    {
      ReleaseGil release;
      auto run = [&](auto dim_tag) {
        constexpr int D = decltype(dim_tag)::value;
        pointwise<D>(Fp, count, out.data(), out_size, [&](const fem::Mat<D>& Fk, Scalar* o) {
          if (kind == 0) {
            o[0] = fem::psi<D>(Fk, mat, mu, lam);
          } else if (kind == 1) {
            const fem::Mat<D> P = fem::piola<D>(Fk, mat, mu, lam);
            for (int r = 0; r < D; ++r)
              for (int c = 0; c < D; ++c) o[r * D + c] = P(r, c);  // row-major for numpy
          } else {
            fem::HessF<D> H = fem::piola_derivative<D>(Fk, mat, mu, lam);
            if (project) fem::project_psd<D>(H);
            Eigen::Map<Eigen::Matrix<Scalar, D * D, D * D, Eigen::RowMajor>> out_H(o);
            out_H = H;
          }
        });
      };
      if (d == 2) run(std::integral_constant<int, 2>{});
      else run(std::integral_constant<int, 3>{});
    }
    std::vector<Index> shape{count};
    if (kind == 1) shape = {count, d, d};
    if (kind == 2) shape = {count, d * d, d * d};
    return to_numpy(std::move(out), shape);
  }, py::arg("F"), py::arg("what"), py::arg("model"), py::arg("mu"), py::arg("lam"),
     py::arg("project") = false);
}

}  // namespace kinema::bind
