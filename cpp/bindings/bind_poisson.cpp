// kinema._core.poisson: the grid Poisson solver object behind km.poisson.
#include <cstdint>
#include <optional>

#include "bindings/common.h"
#include "core/parallel.h"
#include "poisson/poisson_solver.h"

namespace kinema::bind {

namespace {

// Owns the solver and a copy-free reference to nothing else: the solid mask is read once.
struct PySolver {
  PySolver(const std::vector<Index>& shape, Scalar h, Boundary bc,
           std::optional<py::array_t<std::uint8_t, py::array::c_style>> solid, Scalar shift,
           const PoissonConfig& config)
      : shape_(shape), user_shape_(shape) {
    const std::uint8_t* mask = nullptr;
    if (solid) {
      if (solid->size() != shape_.size())
        throw InvalidArgument("solid: expected one flag per cell");
      mask = solid->data();
    }
    ReleaseGil release;
    solver_ = std::make_unique<PoissonSolver>(shape_, h, bc, mask, shift, config);
  }

  py::object solve(py::array b, py::array x, Scalar tol, Index max_iter) {
    const Index n = shape_.size();
    const Scalar* bp = checked_data(b, "f", n, false);
    Scalar* xp = checked_data(x, "x0", n, true);
    IterativeOptions options{tol, max_iter};
    SolveInfo info;
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      info = solver_->solve(bp, xp, options, interrupt);
    }
    return to_python(info);
  }

  py::array_t<Scalar> apply(py::array x, std::optional<py::array> b) {
    const Index n = shape_.size();
    const Scalar* xp = checked_data(x, "u", n, false);
    const Scalar* bp = b ? checked_data(*b, "b", n, false) : nullptr;
    std::vector<Scalar> y(n);
    {
      ReleaseGil release;
      if (bp) solver_->op().residual(bp, xp, y.data());
      else solver_->op().apply(xp, y.data());
    }
    return to_numpy(std::move(y), user_shape_);
  }

  py::array_t<Scalar> vcycle(py::array b) {
    Multigrid* mg = solver_->multigrid();
    if (!mg) throw InvalidArgument("method: vcycle needs method 'multigrid' or 'mgpcg'");
    const Index n = shape_.size();
    const Scalar* bp = checked_data(b, "b", n, false);
    std::vector<Scalar> x(n);
    {
      ReleaseGil release;
      mg->vcycle(bp, x.data());
    }
    return to_numpy(std::move(x), user_shape_);
  }

  // steps of T <- T - c A T (forward Euler for dT/dt = -kappa A T, c = kappa dt), in place.
  void explicit_steps(py::array T, Scalar c, Index steps) {
    const Index n = shape_.size();
    Scalar* t = checked_data(T, "T", n, true);
    std::vector<Scalar> at(n);
    Interrupt interrupt = python_interrupt();
    ReleaseGil release;
    for (Index s = 0; s < steps; ++s) {
      interrupt.check();
      solver_->op().apply(t, at.data());
      parallel_for(n, [&](Index i) { t[i] -= c * at[i]; });
    }
  }

  // Grid transfers between multigrid levels l and l + 1 (for tests).
  py::array_t<Scalar> transfer(int l, py::array in, bool restrict) {
    Multigrid* mg = solver_->multigrid();
    if (!mg) throw InvalidArgument("method: transfers need method 'multigrid' or 'mgpcg'");
    if (l < 0 || l + 1 >= mg->levels()) throw InvalidArgument("l: no such level pair");
    const PoissonOperator& from = mg->level(restrict ? l : l + 1);
    const PoissonOperator& to = mg->level(restrict ? l + 1 : l);
    const Scalar* src = checked_data(in, "in", from.size(), false);
    std::vector<Scalar> out(to.size(), 0);
    if (restrict) mg->restrict_residual(l, src, out.data());
    else mg->prolong_add(l, src, out.data());
    return to_numpy(std::move(out), to.shape().user_shape());
  }

  void project(py::array x) {
    Scalar* xp = checked_data(x, "x", shape_.size(), true);
    ReleaseGil release;
    solver_->op().project(xp);
  }

  Scalar incompatibility(py::array b) {
    const Scalar* bp = checked_data(b, "f", shape_.size(), false);
    ReleaseGil release;
    return solver_->incompatibility(bp);
  }

  py::tuple assemble() {
    CsrArrays A;
    {
      ReleaseGil release;
      A = solver_->op().assemble();
    }
    const Index nnz = static_cast<Index>(A.values.size());
    return py::make_tuple(to_numpy(std::move(A.row_ptr), {A.rows + 1}),
                          to_numpy(std::move(A.col_index), {nnz}),
                          to_numpy(std::move(A.values), {nnz}));
  }

  GridShape shape_;
  std::vector<Index> user_shape_;
  std::unique_ptr<PoissonSolver> solver_;
};

}  // namespace

void bind_poisson(py::module_& m) {
  py::enum_<PoissonMethod>(m, "Method", "Solver of the grid Poisson problem.")
      .value("jacobi", PoissonMethod::Jacobi)
      .value("gauss_seidel", PoissonMethod::GaussSeidel)
      .value("cg", PoissonMethod::CG)
      .value("multigrid", PoissonMethod::Multigrid)
      .value("mgpcg", PoissonMethod::MGPCG);
  py::enum_<Boundary>(m, "Boundary", "Boundary condition on the grid's faces.")
      .value("dirichlet", Boundary::Dirichlet)
      .value("neumann", Boundary::Neumann)
      .value("periodic", Boundary::Periodic);
  py::class_<PoissonConfig>(m, "Config", "How the Poisson problem is solved (poisson/poisson_solver.h).")
      .def(py::init<>())
      .def_readwrite("method", &PoissonConfig::method)
      .def_readwrite("jacobi_omega", &PoissonConfig::jacobi_omega, "damping of the Jacobi iteration")
      .def_property(
          "pre_smooth", [](const PoissonConfig& c) { return c.multigrid.pre_smooth; },
          [](PoissonConfig& c, int n) { c.multigrid.pre_smooth = n; }, "red-black sweeps before the coarse correction")
      .def_property(
          "post_smooth", [](const PoissonConfig& c) { return c.multigrid.post_smooth; },
          [](PoissonConfig& c, int n) { c.multigrid.post_smooth = n; }, "red-black sweeps after it")
      .def_property(
          "coarsest_cells", [](const PoissonConfig& c) { return c.multigrid.coarsest_cells; },
          [](PoissonConfig& c, Index n) { c.multigrid.coarsest_cells = n; }, "stop coarsening at this many cells");
  py::class_<PySolver>(m, "Solver")
      .def(py::init<const std::vector<Index>&, Scalar, Boundary,
                    std::optional<py::array_t<std::uint8_t, py::array::c_style>>, Scalar, const PoissonConfig&>(),
           py::arg("shape"), py::arg("h"), py::arg("bc"), py::arg("solid"), py::arg("shift"), py::arg("config"))
      .def("solve", &PySolver::solve, py::arg("b"), py::arg("x"), py::arg("tol"), py::arg("max_iter"))
      .def("apply", &PySolver::apply, py::arg("x"), py::arg("b") = py::none())
      .def("vcycle", &PySolver::vcycle, py::arg("b"))
      .def("explicit_steps", &PySolver::explicit_steps, py::arg("T"), py::arg("c"), py::arg("steps"))
      .def("transfer", &PySolver::transfer, py::arg("l"), py::arg("x"), py::arg("restrict"))
      .def("project", &PySolver::project, py::arg("x"))
      .def("incompatibility", &PySolver::incompatibility, py::arg("b"))
      .def("assemble", &PySolver::assemble)
      .def("anchor_cells", [](const PySolver& s) {
        auto anchors = s.solver_->op().singular_anchor_cells();
        const Index count = static_cast<Index>(anchors.size());
        return to_numpy(std::move(anchors), {count});
      })
      .def_property_readonly("levels", [](const PySolver& s) {
        auto* mg = s.solver_->multigrid();
        return mg ? mg->levels() : 1;
      })
      .def_property_readonly("singular", [](const PySolver& s) { return s.solver_->op().singular(); })
      .def_property_readonly("fluid_count", [](const PySolver& s) { return s.solver_->op().fluid_count(); })
      .def_property_readonly("default_max_iter", [](const PySolver& s) { return s.solver_->default_max_iter(); });
}

}  // namespace kinema::bind
