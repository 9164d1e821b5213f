// kinema._core.massspring: the mass-spring system (model + state + solver in one object). The
// Python layer (kinema/massspring.py) broadcasts per-item parameters and checks shapes; x and v
// are zero-copy views of the system's own buffers, kept alive by the system.
#include <string>

#include "bindings/common.h"
#include "core/errors.h"
#include "massspring/system.h"

namespace kinema::bind {

namespace {

using massspring::System;

massspring::Integrator parse_integrator(const std::string& name) {
  if (name == "explicit") return massspring::Integrator::Explicit;
  if (name == "symplectic") return massspring::Integrator::Symplectic;
  if (name == "implicit") return massspring::Integrator::Implicit;
  throw InvalidArgument("integrator: expected 'explicit', 'symplectic' or 'implicit', got '" +
                        name + "'");
}

massspring::LinearSolver parse_solver(const std::string& name) {
  if (name == "cholmod") return massspring::LinearSolver::Cholmod;
  if (name == "cg") return massspring::LinearSolver::CG;
  if (name == "cholmod_direct") return massspring::LinearSolver::CholmodDirect;
  if (name == "cholmod_pcg") return massspring::LinearSolver::CholmodPcg;
  throw InvalidArgument("linear_solver: expected 'cholmod', 'cholmod_direct', 'cholmod_pcg' or "
                        "'cg', got '" + name + "'");
}

py::array view(py::object self, std::vector<Scalar>& buffer, Index d) {
  const Index rows = static_cast<Index>(buffer.size()) / d;
  return py::array_t<Scalar>({rows, d}, buffer.data(), self);
}

}  // namespace

void bind_massspring(py::module_& m) {
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
             massspring::SystemModel model = massspring::make_system(
                 d, n, springs.data(), count, stiffness.data(), rest_length.data(),
                 damping.data(), mass.data(), fixed.data(), fixed.size(), gravity);
             return std::make_unique<System>(std::move(model), x.data());
           }),
           py::arg("x"), py::arg("springs"), py::arg("stiffness"), py::arg("rest_length"),
           py::arg("damping"), py::arg("mass"), py::arg("fixed"), py::arg("gravity"))
      .def_property_readonly("x", [](py::object self) {
        System& s = self.cast<System&>();
        return view(self, s.state().x, s.model().dim);
      })
      .def_property_readonly("v", [](py::object self) {
        System& s = self.cast<System&>();
        return view(self, s.state().v, s.model().dim);
      })
      // Settable for checkpoints (km.Scene resumes a run bit for bit).
      .def_property("time", [](System& s) { return s.state().time; },
                    [](System& s, Scalar t) { s.state().time = t; })
      .def_property("step_count", [](System& s) { return s.state().step; },
                    [](System& s, Index n) { s.state().step = n; })
      .def_property_readonly("explicit_dt_limit", &System::explicit_dt_limit)
      .def("step",
           [](System& s, Scalar dt, const std::string& integrator, Scalar beta,
              const std::string& solver, Scalar cg_tol, Index steps) {
             const auto kind = parse_integrator(integrator);
             const auto lin = parse_solver(solver);
             Interrupt interrupt = python_interrupt();
             massspring::StepStats stats, last;
             {
               ReleaseGil release;
               for (Index k = 0; k < steps; ++k) {
                 interrupt.check();
                 last = with_rollback(s.state(), [&] { return s.step(dt, kind, beta, lin, cg_tol, interrupt); });
                 stats.clamped = stats.clamped || last.clamped;
                 stats.refactored = stats.refactored || last.refactored;
                 stats.cg_iterations += last.cg_iterations;
                 stats.factorizations += last.factorizations;
                 stats.seconds_assembly += last.seconds_assembly;
                 stats.seconds_factor += last.seconds_factor;
                 stats.seconds_solve += last.seconds_solve;
                 stats.seconds += last.seconds;
               }
             }
             py::dict d;
             d["clamped"] = stats.clamped;
             d["refactored"] = stats.refactored;
             d["cg_iterations"] = stats.cg_iterations;
             d["factorizations"] = stats.factorizations;
             d["seconds_assembly"] = stats.seconds_assembly;
             d["seconds_factor"] = stats.seconds_factor;
             d["seconds_solve"] = stats.seconds_solve;
             d["seconds"] = stats.seconds;
             return d;
           },
           py::arg("dt"), py::arg("integrator"), py::arg("beta"), py::arg("linear_solver"),
           py::arg("cg_tol"), py::arg("steps"))
      .def("kinetic_energy", &System::kinetic_energy)
      .def("spring_energy", &System::spring_energy)
      .def("gravity_energy", &System::gravity_energy)
      .def("forces", [](System& s) {
        std::vector<Scalar> f(s.state().x.size());
        s.forces(f.data());
        const Index d = s.model().dim;
        const Index n = static_cast<Index>(f.size()) / d;
        return to_numpy(std::move(f), {n, d});
      });
}

}  // namespace kinema::bind
