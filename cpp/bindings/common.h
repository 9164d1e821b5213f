// Shared helpers of the bindings: numpy array conventions, GIL release with Ctrl-C polling,
// and SolveInfo conversion. Zero-copy: arrays are accepted as C-contiguous float64/int64
// (the Python layer converts once, with np.ascontiguousarray), never copied again here.
#pragma once

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <string>
#include <vector>

#include "core/interrupt.h"
#include "core/parallel.h"
#include "core/rollback.h"
#include "core/types.h"
#include "linalg/solve_info.h"

namespace kinema::bind {

namespace py = pybind11;

using ScalarArray = py::array_t<Scalar, py::array::c_style>;
using IndexArray = py::array_t<Index, py::array::c_style>;

// An Interrupt whose poll briefly takes the GIL and runs Python's signal handlers, so that
// Ctrl-C stops a GIL-released computation within about 0.1 s.
inline Interrupt python_interrupt() {
  return Interrupt([] {
    py::gil_scoped_acquire gil;
    return PyErr_CheckSignals() != 0;
  });
}

// Releases the GIL for a long call, which then runs with kinema's process-wide thread count
// (km.set_num_threads) whichever Python thread makes it.
struct ReleaseGil {
  ReleaseGil() { use_thread_count_setting(); }
  py::gil_scoped_release release;
};

// The Python-side SolveInfo class lives in kinema/_info.py; build one from the C++ record.
inline py::object to_python(const SolveInfo& info) {
  return py::module_::import("kinema._info").attr("SolveInfo")(
      info.iterations, info.residual, info.converged, info.history, info.seconds);
}

std::vector<Index> shape_of(const py::array& a);

// The data of a C-contiguous float64 array of `size` elements (writable when `writable`), or a
// ValueError naming `name`. Never converts: an in/out array must be the caller's own memory.
Scalar* checked_data(py::array& a, const char* name, Index size, bool writable);

// Hands a vector's buffer to numpy without copying; the array owns it through a capsule.
template <class T>
py::array_t<T> to_numpy(std::vector<T>&& v, const std::vector<Index>& shape) {
  auto* owner = new std::vector<T>(std::move(v));
  py::capsule capsule(owner, [](void* p) { delete static_cast<std::vector<T>*>(p); });
  std::vector<py::ssize_t> dims(shape.begin(), shape.end());
  return py::array_t<T>(dims, owner->data(), capsule);
}

}  // namespace kinema::bind
