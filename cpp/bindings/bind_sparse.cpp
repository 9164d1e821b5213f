// kinema._core.sparse: CHOLMOD factor and CG on scipy's CSR arrays (zero-copy). The Python
// layer (kinema/sparse.py) converts and checks the matrix; here only the array lengths are
// checked, the C++ core checks the pattern itself.
#include <chrono>
#include <condition_variable>
#include <exception>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "bindings/common.h"
#include "core/errors.h"
#include "linalg/cg.h"
#include "linalg/cholmod_factor.h"
#include "linalg/csr.h"

namespace kinema::bind {

namespace {

std::string str(Index i) { return std::to_string(i); }

// scipy's default index arrays, taken as they are (no conversion to 64 bits) where the core
// reads both widths.
using Index32Array = py::array_t<std::int32_t, py::array::c_style>;

// indptr, indices, data of an n x n CSR matrix, checked only for lengths, so that the core may
// read indptr[0..n] and indptr[n] entries of the others.
template <class Indices>
void check_lengths(Index n, const Indices& indptr, const Indices& indices, const ScalarArray& data) {
  if (n < 0) throw InvalidArgument("n: expected >= 0, got " + str(n));
  if (indptr.ndim() != 1 || indptr.size() != n + 1)
    throw InvalidArgument("A.indptr: expected " + str(n + 1) + " entries, got " +
                          str(indptr.size()));
  if (indices.ndim() != 1 || data.ndim() != 1 || indices.size() != data.size())
    throw InvalidArgument("A: indices and data must be 1-D of equal length, got " +
                          str(indices.size()) + " and " + str(data.size()));
  const Index nnz = static_cast<Index>(indptr.data()[n]);
  if (nnz < 0 || nnz > indices.size())
    throw InvalidArgument("A.indptr: last entry " + str(nnz) + " is outside [0, " +
                          str(indices.size()) + "], the number of stored entries");
}

std::string shape_str(const py::array& a) {
  std::string s = "(";
  for (py::ssize_t d = 0; d < a.ndim(); ++d) s += (d ? ", " : "") + str(a.shape(d));
  return s + (a.ndim() == 1 ? ",)" : ")");
}

// A symmetric matrix's CSR arrays are its CSC arrays.
template <class Indices>
auto csc_view(Index n, const Indices& indptr, const Indices& indices, const ScalarArray& data) {
  check_lengths(n, indptr, indices, data);
  using I = typename Indices::value_type;
  return BasicCscView<I>{n, n, indptr.data(), indices.data(), data.data()};
}

// CHOLMOD cannot stop midway through a factorisation (a large one takes seconds), so it runs
// on a thread of its own while the caller answers Ctrl-C. On Ctrl-C the caller returns at once;
// the thread finishes on its own copy of the matrix and frees the abandoned factor.
template <class I>
std::unique_ptr<CholmodFactor> factor_interruptibly(const BasicCscView<I>& A, CholmodOrdering order) {
  struct Job {
    std::vector<I> col_ptr, row_index;
    std::vector<Scalar> values;
    std::mutex mutex;
    std::condition_variable finished;
    bool done = false;
    std::unique_ptr<CholmodFactor> factor;
    std::exception_ptr error;
  };
  auto job = std::make_shared<Job>();
  const auto nnz = static_cast<size_t>(A.col_ptr[A.cols]);
  job->col_ptr.assign(A.col_ptr, A.col_ptr + A.cols + 1);
  job->row_index.assign(A.row_index, A.row_index + nnz);
  job->values.assign(A.values, A.values + nnz);
  const Index rows = A.rows, cols = A.cols;
  std::thread([job, rows, cols, order] {
    use_thread_count_setting();
    std::unique_ptr<CholmodFactor> factor;
    std::exception_ptr error;
    try {
      const BasicCscView<I> copy{rows, cols, job->col_ptr.data(), job->row_index.data(), job->values.data()};
      factor = std::make_unique<CholmodFactor>(copy, order);
    } catch (...) {
      error = std::current_exception();
    }
    std::lock_guard<std::mutex> lock(job->mutex);
    job->factor = std::move(factor);
    job->error = error;
    job->done = true;
    job->finished.notify_all();
  }).detach();
  Interrupt interrupt = python_interrupt();
  std::unique_lock<std::mutex> lock(job->mutex);
  while (!job->finished.wait_for(lock, std::chrono::milliseconds(20), [&] { return job->done; })) {
    lock.unlock();
    interrupt.check();
    lock.lock();
  }
  if (job->error) std::rethrow_exception(job->error);
  return std::move(job->factor);
}

CholmodOrdering parse_ordering(const std::string& name) {
  if (name == "default") return CholmodOrdering::Default;
  if (name == "amd") return CholmodOrdering::Amd;
  if (name == "natural") return CholmodOrdering::Natural;
  if (name == "metis") return CholmodOrdering::Metis;
  throw InvalidArgument("ordering: expected 'default', 'amd', 'metis' or 'natural', got '" + name + "'");
}

// Factor(n, indptr, indices, data, ordering) and Factor.refactor for one index width.
template <class Indices>
void bind_factor_arrays(py::class_<CholmodFactor>& factor) {
  factor
      .def(py::init([](Index n, const Indices& indptr, const Indices& indices, const ScalarArray& data,
                       const std::string& ordering) {
             const auto A = csc_view(n, indptr, indices, data);
             const CholmodOrdering order = parse_ordering(ordering);
             ReleaseGil release;
             return factor_interruptibly(A, order);
           }),
           py::arg("n"), py::arg("indptr"), py::arg("indices"), py::arg("data"),
           py::arg("ordering") = "default")
      .def(
          "refactor",
          [](CholmodFactor& f, Index n, const Indices& indptr, const Indices& indices,
             const ScalarArray& data) {
            const auto A = csc_view(n, indptr, indices, data);
            ReleaseGil release;
            f.refactor(A);
          },
          py::arg("n"), py::arg("indptr"), py::arg("indices"), py::arg("data"));
}

template <class Indices>
py::tuple asymmetry_of(Index n, const Indices& indptr, const Indices& indices, const ScalarArray& data) {
  check_lengths(n, indptr, indices, data);
  using I = typename Indices::value_type;
  const BasicCsrView<I> A{n, n, indptr.data(), indices.data(), data.data()};
  Asymmetry a;
  {
    ReleaseGil release;
    a = asymmetry(A);
  }
  return py::make_tuple(a.value, a.row, a.col);
}


}  // namespace

void bind_sparse(py::module_& m) {
  py::class_<CholmodFactor> factor(m, "Factor");
  // int32 index arrays first: overload resolution then takes scipy's default arrays as they are.
  bind_factor_arrays<Index32Array>(factor);
  bind_factor_arrays<IndexArray>(factor);
  factor
      // b: (n,) or (k, n) C-contiguous, i.e. k right-hand sides stored column-major n x k.
      .def(
          "solve",
          [](const CholmodFactor& f, const ScalarArray& b) {
            const Index n = f.size();
            const bool one = b.ndim() == 1 && b.shape(0) == n;
            const bool many = b.ndim() == 2 && b.shape(1) == n;
            if (!one && !many)
              throw InvalidArgument("b: expected shape (" + str(n) + ",) or (k, " + str(n) +
                                    "), got " + shape_str(b));
            const Index nrhs = one ? 1 : b.shape(0);
            ScalarArray x(shape_of(b));
            const Scalar* bp = b.data();
            Scalar* xp = x.mutable_data();
            {
              ReleaseGil release;
              f.solve(bp, xp, nrhs);
            }
            return x;
          },
          py::arg("b"))
      .def_property_readonly("n", &CholmodFactor::size)
      .def_property_readonly("nnz_factor", &CholmodFactor::factor_nonzeros)
      .def_property_readonly("is_supernodal", &CholmodFactor::is_supernodal)
      .def_property_readonly("index_bits", &CholmodFactor::index_bits)
      .def_property_readonly("permutation",
                             [](const CholmodFactor& f) {
                               const Index* p = f.permutation();
                               return IndexArray(f.size(), p);  // a copy
                             })
      .def("logdet", &CholmodFactor::log_determinant);

  m.def("asymmetry", &asymmetry_of<Index32Array>, py::arg("n"), py::arg("indptr"), py::arg("indices"),
        py::arg("data"));
  m.def("asymmetry", &asymmetry_of<IndexArray>, py::arg("n"), py::arg("indptr"), py::arg("indices"),
        py::arg("data"));

  // x holds the initial guess and receives the solution in place (no conversion allowed, so
  // the caller's array is the one written).
  m.def(
      "cg",
      [](Index n, const IndexArray& indptr, const IndexArray& indices, const ScalarArray& data,
         const ScalarArray& b, ScalarArray x, bool jacobi, Scalar tol, Index max_iter) {
        check_lengths(n, indptr, indices, data);
        if (b.ndim() != 1 || b.size() != n)
          throw InvalidArgument("b: expected shape (" + str(n) + ",), got " + str(b.size()) +
                                " entries");
        if (x.ndim() != 1 || x.size() != n)
          throw InvalidArgument("x: expected shape (" + str(n) + ",), got " + str(x.size()) +
                                " entries");
        const CsrView A{n, n, indptr.data(), indices.data(), data.data()};
        const IterativeOptions options{tol, max_iter};
        const Scalar* bp = b.data();
        Scalar* xp = x.mutable_data();
        Interrupt interrupt = python_interrupt();
        SolveInfo info;
        {
          ReleaseGil release;
          info = cg_csr(A, bp, xp, jacobi, options, interrupt);
        }
        return to_python(info);
      },
      py::arg("n"), py::arg("indptr"), py::arg("indices"), py::arg("data"), py::arg("b"),
      py::arg("x").noconvert(), py::arg("jacobi"), py::arg("tol"), py::arg("max_iter"));
}

}  // namespace kinema::bind
