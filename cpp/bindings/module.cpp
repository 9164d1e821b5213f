// The single extension module kinema._core, one submodule per method. Users never import it
// directly: python/kinema/ wraps it with argument checking and documentation.
#include <pybind11/pybind11.h>

#include <string>

#include "bindings/common.h"
#include "core/build_info.h"
#include "core/errors.h"
#include "core/parallel.h"
#include "core/step_stats.h"
#include "linalg/spd_solver.h"

namespace py = pybind11;

namespace kinema::bind {

void bind_sparse(py::module_& m);
void bind_poisson(py::module_& m);
void bind_fmm(py::module_& m);
void bind_grid(py::module_& m);
void bind_massspring(py::module_& m);
void bind_fem(py::module_& m);
void bind_sph(py::module_& m);
void bind_render(py::module_& m);
void bind_mpm(py::module_& m);
void bind_contact(py::module_& m);

std::vector<Index> shape_of(const py::array& a) {
  return std::vector<Index>(a.shape(), a.shape() + a.ndim());
}

Scalar* checked_data(py::array& a, const char* name, Index size, bool writable) {
  if (!a.dtype().is(py::dtype::of<Scalar>()))
    throw InvalidArgument(std::string(name) + ": expected a float64 array");
  if (!(a.flags() & py::array::c_style))
    throw InvalidArgument(std::string(name) + ": expected a C-contiguous array");
  if (writable && !a.writeable()) throw InvalidArgument(std::string(name) + ": array is read-only");
  if (a.size() != size)
    throw InvalidArgument(std::string(name) + ": expected " + std::to_string(size) +
                          " elements, got " + std::to_string(a.size()));
  return static_cast<Scalar*>(a.mutable_data());
}

namespace {

// Raises the Python class kinema.errors.<name> with the given message. The classes are defined
// in Python so they can inherit from both KinemaError and ValueError.
void raise(const char* name, const char* message, py::object column = py::none()) {
  py::object cls = py::module_::import("kinema.errors").attr(name);
  py::object exc = cls(message);
  if (!column.is_none()) exc.attr("column") = column;
  PyErr_SetObject(cls.ptr(), exc.ptr());
}

void translate_exceptions() {
  py::register_exception_translator([](std::exception_ptr p) {
    try {
      if (p) std::rethrow_exception(p);
    } catch (const Interrupted&) {
      // Python's own handler already set KeyboardInterrupt when PyErr_CheckSignals failed.
      if (!PyErr_Occurred()) PyErr_SetNone(PyExc_KeyboardInterrupt);
    } catch (const NotPositiveDefinite& e) {
      raise("NotPositiveDefiniteError", e.what(), py::int_(e.column));
    } catch (const StabilityError& e) {
      raise("StabilityError", e.what());
    } catch (const ConvergenceError& e) {
      raise("ConvergenceError", e.what());
    } catch (const DivergenceError& e) {
      raise("DivergenceError", e.what());
    } catch (const KinemaError& e) {
      raise("KinemaError", e.what());
    } catch (const InvalidArgument& e) {
      PyErr_SetString(PyExc_ValueError, e.what());
    }
  });
}

}  // namespace

}  // namespace kinema::bind

PYBIND11_MODULE(_core, m) {
  using namespace kinema;
  m.doc() = "kinema's compiled core; use the kinema package, not this module.";
  bind::translate_exceptions();

  m.def("set_num_threads", [](long long n) {
    if (n < 1 || n > max_thread_count())
      throw InvalidArgument("n: expected a thread count in [1, " + std::to_string(max_thread_count()) + "], got " +
                            std::to_string(n));
    set_num_threads(static_cast<int>(n));
  });
  m.def("get_num_threads", &configured_num_threads);
  m.def("max_num_threads", &max_thread_count);
  m.def("build_info", &build_info);

  // The base of every method's StepStats (core/step_stats.h), registered before the
  // submodules so that theirs can name it as their base class.
  py::class_<StepStatsBase>(m, "StepStats", "Fields every method's step statistics share.")
      // Constructible for the methods whose time stepping is written in Python (km.nbody, km.vortex).
      .def(py::init([](Scalar time, Scalar dt, double seconds) { return StepStatsBase{time, dt, seconds}; }),
           py::kw_only(), py::arg("time"), py::arg("dt"), py::arg("seconds"))
      .def_readonly("time", &StepStatsBase::time, "simulated time at the end of the step [s]")
      .def_readonly("dt", &StepStatsBase::dt, "the step taken [s]")
      .def_readonly("seconds", &StepStatsBase::seconds, "wall time of the step [s]")
      .def("__repr__", [](const StepStatsBase& s) {
        return "StepStats(time=" + format_real(s.time) + ", dt=" + format_real(s.dt) +
               ", seconds=" + format_real(s.seconds) + ")";
      });
  // The SPD solve dispatch of the implicit mechanics methods (linalg/spd_solver.h), shared by
  // their Configs, so registered once here.
  py::enum_<LinearSolver>(m, "LinearSolver")
      .value("cholmod", LinearSolver::Cholmod)
      .value("cholmod_direct", LinearSolver::CholmodDirect)
      .value("cholmod_pcg", LinearSolver::CholmodPcg)
      .value("cg", LinearSolver::CG);

  auto sparse = m.def_submodule("sparse");
  bind::bind_sparse(sparse);
  auto poisson = m.def_submodule("poisson");
  bind::bind_poisson(poisson);
  auto fmm = m.def_submodule("fmm");
  bind::bind_fmm(fmm);
  auto grid = m.def_submodule("grid");
  bind::bind_grid(grid);
  auto massspring = m.def_submodule("massspring");
  bind::bind_massspring(massspring);
  auto fem = m.def_submodule("fem");
  bind::bind_fem(fem);
  auto sph = m.def_submodule("sph");
  bind::bind_sph(sph);
  auto render = m.def_submodule("render");
  bind::bind_render(render);
  auto mpm = m.def_submodule("mpm");
  bind::bind_mpm(mpm);
  auto contact = m.def_submodule("contact");
  bind::bind_contact(contact);
}
