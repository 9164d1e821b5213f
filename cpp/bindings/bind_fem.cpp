// kinema._core.fem: the finite-element body (model + state + solver in one object) and the
// pointwise material functions. The Python layer (kinema/fem.py) checks shapes and names; the
// state arrays x, v are zero-copy views of the body's own buffers, kept alive by the body.
#include <string>
#include <type_traits>

#include "bindings/common.h"
#include "core/errors.h"
#include "core/parallel.h"
#include "fem/body.h"

namespace kinema::bind {

namespace {

using fem::Body;

fem::Material parse_material(const std::string& name) {
  if (name == "linear") return fem::Material::Linear;
  if (name == "stvk") return fem::Material::StVK;
  if (name == "corotated") return fem::Material::Corotated;
  if (name == "neohookean") return fem::Material::NeoHookean;
  throw InvalidArgument("model: expected 'linear', 'stvk', 'corotated' or 'neohookean', got '" +
                        name + "'");
}

fem::Definiteness parse_definiteness(const std::string& name) {
  if (name == "adaptive") return fem::Definiteness::Adaptive;
  if (name == "project") return fem::Definiteness::Project;
  if (name == "none") return fem::Definiteness::None;
  throw InvalidArgument("definiteness: expected 'adaptive', 'project' or 'none', got '" + name + "'");
}

fem::LinearSolver parse_solver(const std::string& name) {
  if (name == "cholmod") return fem::LinearSolver::Cholmod;
  if (name == "cg") return fem::LinearSolver::CG;
  if (name == "cholmod_direct") return fem::LinearSolver::CholmodDirect;
  if (name == "cholmod_pcg") return fem::LinearSolver::CholmodPcg;
  throw InvalidArgument("linear_solver: expected 'cholmod', 'cholmod_direct', 'cholmod_pcg' or "
                        "'cg', got '" + name + "'");
}

py::dict stats_dict(const fem::NewtonStats& s) {
  py::dict d;
  d["iterations"] = s.iterations;
  d["converged"] = s.converged;
  d["gradient_norm"] = s.gradient_norm;
  d["step_length"] = s.step_length;
  d["projected_elements"] = s.projected_elements;
  d["cg_iterations"] = s.cg_iterations;
  d["factorizations"] = s.factorizations;
  d["seconds_assembly"] = s.seconds_assembly;
  d["seconds_factor"] = s.seconds_factor;
  d["seconds_solve"] = s.seconds_solve;
  d["seconds_line_search"] = s.seconds_line_search;
  d["seconds"] = s.seconds;
  return d;
}

// A (rows, d) view of a state buffer owned by the body behind `self`.
py::array view(py::object self, std::vector<Scalar>& buffer, Index d) {
  const Index rows = static_cast<Index>(buffer.size()) / d;
  return py::array_t<Scalar>({rows, d}, buffer.data(), self);
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
  py::class_<Body>(m, "Body")
      .def(py::init([](const ScalarArray& vertices, const IndexArray& elements,
                       const std::string& material, Scalar E, Scalar nu, Scalar rho,
                       const IndexArray& fixed, std::vector<Scalar> gravity, Scalar damping) {
             if (vertices.ndim() != 2) throw InvalidArgument("vertices: expected shape (n, d)");
             const int d = static_cast<int>(vertices.shape(1));
             if (elements.ndim() != 2 || elements.shape(1) != d + 1)
               throw InvalidArgument("elements: expected shape (m, " + std::to_string(d + 1) + ")");
             fem::BodyConfig config;
             config.material = parse_material(material);
             config.youngs_modulus = E;
             config.poisson_ratio = nu;
             config.density = rho;
             config.damping = damping;
             config.gravity = std::move(gravity);
             ReleaseGil release;
             fem::BodyModel model =
                 fem::make_model(d, vertices.data(), vertices.shape(0), elements.data(),
                                 elements.shape(0), config, fixed.data(), fixed.size());
             return std::make_unique<Body>(std::move(model), config);
           }),
           py::arg("vertices"), py::arg("elements"), py::arg("model"), py::arg("youngs_modulus"),
           py::arg("poisson_ratio"), py::arg("density"), py::arg("fixed"), py::arg("gravity"),
           py::arg("damping"))
      .def_property_readonly("x", [](py::object self) {
        Body& b = self.cast<Body&>();
        return view(self, b.state().x, b.model().dim);
      })
      .def_property_readonly("v", [](py::object self) {
        Body& b = self.cast<Body&>();
        return view(self, b.state().v, b.model().dim);
      })
      .def_property_readonly("rest", [](const Body& b) {
        const auto& r = b.model().rest;
        const Index d = b.model().dim;
        return py::array_t<Scalar>({static_cast<Index>(r.size()) / d, d}, r.data());  // a copy
      })
      .def_property_readonly("mass", [](const Body& b) {
        return py::array_t<Scalar>(b.model().vertex_count, b.model().mass.data());
      })
      .def_property_readonly("volume", [](const Body& b) {
        return py::array_t<Scalar>(b.model().element_count, b.model().volume.data());
      })
      .def_property_readonly("mu", [](const Body& b) { return b.model().mu; })
      .def_property_readonly("lam", [](const Body& b) { return b.model().lam; })
      // Settable for checkpoints (km.Scene resumes a run bit for bit).
      .def_property("time", [](const Body& b) { return b.state().time; },
                    [](Body& b, Scalar t) { b.state().time = t; })
      .def_property("step_count", [](const Body& b) { return b.state().step; },
                    [](Body& b, Index n) { b.state().step = n; })
      .def_property_readonly("explicit_dt_limit", &Body::explicit_dt_limit)
      .def("step_implicit",
           [](Body& b, Scalar dt, Scalar tol, Index max_newton, const std::string& solver,
              Scalar cg_tol, const std::string& definiteness) {
             fem::NewtonOptions options;
             options.definiteness = parse_definiteness(definiteness);
             options.tol = tol;
             options.max_iter = max_newton;
             options.linear_solver = parse_solver(solver);
             options.cg_tol = cg_tol;
             Interrupt interrupt = python_interrupt();
             fem::NewtonStats stats;
             {
               ReleaseGil release;
               stats = with_rollback(b.state(), [&] { return b.step_implicit(dt, options, interrupt); });
             }
             return stats_dict(stats);
           },
           py::arg("dt"), py::arg("tol"), py::arg("max_newton"), py::arg("linear_solver"),
           py::arg("cg_tol"), py::arg("definiteness"))
      .def("step_symplectic",
           [](Body& b, Scalar dt, Index steps) {
             Interrupt interrupt = python_interrupt();
             ReleaseGil release;
             for (Index s = 0; s < steps; ++s) {
               interrupt.check();
               with_rollback(b.state(), [&] { b.step_symplectic(dt); });
             }
           },
           py::arg("dt"), py::arg("steps"))
      .def("solve_static",
           [](Body& b, Scalar tol, Index max_iter, Index load_steps, const std::string& solver,
              const std::string& definiteness) {
             fem::NewtonOptions options;
             options.definiteness = parse_definiteness(definiteness);
             options.tol = tol;
             options.max_iter = max_iter;
             options.linear_solver = parse_solver(solver);
             Interrupt interrupt = python_interrupt();
             fem::NewtonStats stats;
             {
               ReleaseGil release;
               stats = with_rollback(b.state(), [&] { return b.solve_static(options, load_steps, interrupt); });
             }
             return stats_dict(stats);
           },
           py::arg("tol"), py::arg("max_iter"), py::arg("load_steps"), py::arg("linear_solver"),
           py::arg("definiteness"))
      .def("elastic_energy", [](const Body& b) { return b.elastic_energy(b.state().x.data()); })
      .def("kinetic_energy", &Body::kinetic_energy)
      .def("gravity_energy", [](const Body& b) { return b.gravity_energy(b.state().x.data()); })
      .def("forces", [](Body& b) {
        std::vector<Scalar> f(b.state().x.size());
        {
          ReleaseGil release;
          b.forces(b.state().x.data(), f.data());
        }
        const Index d = b.model().dim;
        const Index n = static_cast<Index>(f.size()) / d;
        return to_numpy(std::move(f), {n, d});
      })
      .def("hessian", [](Body& b, bool project) {
        const ElementAssembly& p = b.pattern();
        std::vector<Scalar> values(p.nonzeros());
        {
          ReleaseGil release;
          b.projected_hessian(b.state().x.data(), project, values.data());
        }
        std::vector<Index> row_ptr = p.row_ptr(), col = p.col_index();
        const Index nnz = p.nonzeros();
        return py::make_tuple(to_numpy(std::move(row_ptr), {p.dof_count() + 1}),
                              to_numpy(std::move(col), {nnz}), to_numpy(std::move(values), {nnz}));
      }, py::arg("project"));

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
