#include "linalg/lagged_cholesky.h"

#include <dlfcn.h>
#include <omp.h>

#include "core/errors.h"
#include "core/timer.h"

namespace kinema {

namespace {

// OpenBLAS's threads help CHOLMOD's factorisation (dense BLAS-3 on supernodes) but slow its
// triangular solves, a sequence of small BLAS-2 calls that each pay a thread hand-off, with
// kinema's OpenMP threads still spinning beside them (34k-tet cube, 2 cores: one solve 12 ms
// with one BLAS thread, 29-78 ms with two). Solves run with one BLAS thread for the scope of
// this guard. The BLAS thread count is process-wide, so a factorisation running at the same
// time in another thread may run single-threaded for a while: slower, never wrong. A no-op
// for a BLAS other than OpenBLAS (looked up at run time, as core/build_info.cpp does).
class OneBlasThread {
 public:
  OneBlasThread() {
    if (!get_ || !set_) return;
    saved_ = get_();
    if (saved_ > 1) set_(1);
  }
  ~OneBlasThread() {
    if (saved_ > 1) set_(saved_);
  }
  OneBlasThread(const OneBlasThread&) = delete;
  OneBlasThread& operator=(const OneBlasThread&) = delete;

 private:
  using Get = int (*)();
  using Set = void (*)(int);
  inline static const Get get_ =
      reinterpret_cast<Get>(dlsym(RTLD_DEFAULT, "openblas_get_num_threads"));
  inline static const Set set_ =
      reinterpret_cast<Set>(dlsym(RTLD_DEFAULT, "openblas_set_num_threads"));
  int saved_ = 0;
};

// PCG with a Cholesky preconditioner spends its time in the (serial) triangular solves; its
// vector operations and product on a few 10^4 unknowns take a fraction of a millisecond, less
// than waking a thread team costs on a busy machine (each parallel region then waits for a
// descheduled thread: 129^2 cloth, another process on one of 2 cores, 3.9 PCG iterations
// took 266 ms per step). So PCG runs on the calling thread: omp_set_num_threads sets the
// calling thread's own team size (an OpenMP per-task setting), restored on exit; kinema's
// reductions give bitwise the same result for any thread count.
class OneOmpThread {
 public:
  OneOmpThread() : saved_(omp_get_max_threads()) { omp_set_num_threads(1); }
  ~OneOmpThread() { omp_set_num_threads(saved_); }
  OneOmpThread(const OneOmpThread&) = delete;
  OneOmpThread& operator=(const OneOmpThread&) = delete;

 private:
  int saved_;
};

}  // namespace

bool LaggedCholesky::solve(const CsrView& A, const Scalar* b, Scalar* x, bool reuse, Scalar tol,
                           Index max_pcg, LaggedSolveStats& stats) {
  const Index n = A.rows;
  Stopwatch phase;
  if (reuse && has_factor() && !refactor_next_) {
    const LinearOperator op = [&](const Scalar* v, Scalar* y) { spmv(A, v, y); };
    const LinearOperator pre = [&](const Scalar* r, Scalar* z) { factor_->solve(r, z, 1); };
    OneBlasThread single;
    OneOmpThread serial;
    Interrupt none;
    bool converged = false;
    try {
      const SolveInfo info =
          pcg(n, op, pre, b, x, IterativeOptions{tol, max_pcg}, none, {}, &workspace_);
      stats.pcg_iterations += info.iterations;
      converged = info.converged;
      refactor_next_ = info.iterations > max_pcg / 2;
    } catch (const InvalidArgument&) {
      // pcg's only InvalidArgument: a direction p with p^T A p <= 0, a certificate that A is
      // not positive definite; no factorisation is needed to tell, and the lagged factor
      // stays as the preconditioner of the definite matrix the caller will try next.
      stats.seconds_solve += phase.seconds();
      return false;
    }
    stats.seconds_solve += phase.seconds();
    if (converged) return true;
    phase.restart();
  }
  const CscView C{n, n, A.row_ptr, A.col_index, A.values};
  ++stats.factorizations;
  refactor_next_ = false;
  try {
    if (!factor_) factor_ = std::make_unique<CholmodFactor>(C);
    else factor_->refactor(C);
  } catch (const NotPositiveDefinite&) {
    valid_ = false;
    stats.seconds_factor += phase.seconds();
    return false;
  }
  valid_ = true;
  stats.seconds_factor += phase.seconds();
  phase.restart();
  OneBlasThread single;
  factor_->solve(b, x, 1);
  stats.seconds_solve += phase.seconds();
  return true;
}

void LaggedCholesky::solve_with_factor(const Scalar* b, Scalar* x) const {
  if (!has_factor()) throw KinemaError("solve_with_factor: no valid CHOLMOD factor");
  OneBlasThread single;
  factor_->solve(b, x, 1);
}

}  // namespace kinema
