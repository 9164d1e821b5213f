#include "linalg/cholmod_factor.h"

#include <cholmod.h>

#include <algorithm>
#include <cmath>
#include <mutex>
#include <new>
#include <string>
#include <type_traits>
#include <vector>

#include "core/errors.h"

namespace kinema {

static_assert(sizeof(SuiteSparse_long) == sizeof(Index) &&
                  std::is_signed_v<SuiteSparse_long>,
              "CHOLMOD's long interface must use kinema's 64-bit Index");

namespace {

// CHOLMOD's error handler has no user pointer; the message of the last error raised on this
// thread is kept here and read right after the call that raised it (CHOLMOD reports on the
// calling thread). Printing is off (Common.print = 0): the message travels in the exception.
thread_local std::string cholmod_message;

void record_error(int status, const char* file, int line, const char* message) {
  cholmod_message = std::string(message ? message : "") + " (status " + std::to_string(status) +
                    ", " + (file ? file : "?") + ":" + std::to_string(line) + ")";
}

std::string str(Index i) { return std::to_string(i); }

// Square, non-empty, col_ptr monotone from 0, row indices in range and strictly increasing
// within a column (sorted, no duplicates: CHOLMOD would otherwise read them inconsistently),
// finite values. O(nnz), far below the cost of a factorisation.
void check_view(const CscView& A) {
  if (A.rows != A.cols)
    throw InvalidArgument("A: expected a square matrix, got " + str(A.rows) + " x " + str(A.cols));
  if (A.rows <= 0) throw InvalidArgument("A: expected a non-empty matrix, got 0 x 0");
  if (!A.col_ptr) throw InvalidArgument("A: col_ptr is null");
  const Index n = A.cols;
  if (A.col_ptr[0] != 0)
    throw InvalidArgument("A: col_ptr[0] must be 0, got " + str(A.col_ptr[0]));
  for (Index j = 0; j < n; ++j)
    if (A.col_ptr[j + 1] < A.col_ptr[j])
      throw InvalidArgument("A: col_ptr must be non-decreasing, but col_ptr[" + str(j + 1) +
                            "] = " + str(A.col_ptr[j + 1]) + " < col_ptr[" + str(j) +
                            "] = " + str(A.col_ptr[j]));
  if (A.col_ptr[n] > 0 && (!A.row_index || !A.values))
    throw InvalidArgument("A: row_index or values is null for " + str(A.col_ptr[n]) + " entries");
  for (Index j = 0; j < n; ++j) {
    for (Index p = A.col_ptr[j]; p < A.col_ptr[j + 1]; ++p) {
      const Index i = A.row_index[p];
      if (i < 0 || i >= n)
        throw InvalidArgument("A: row index " + str(i) + " of column " + str(j) +
                              " is outside [0, " + str(n) + ")");
      if (p > A.col_ptr[j] && i <= A.row_index[p - 1])
        throw InvalidArgument("A: row indices of column " + str(j) +
                              " must be strictly increasing (sorted, no duplicates), got " +
                              str(A.row_index[p - 1]) + " then " + str(i));
      if (!std::isfinite(A.values[p]))
        throw InvalidArgument("A: non-finite value " + std::to_string(A.values[p]) + " at (" +
                              str(i) + ", " + str(j) + ")");
    }
  }
}

// The borrowed arrays seen as a CHOLMOD matrix, without copying. stype = -1: CHOLMOD reads
// only the lower triangle. CHOLMOD's analysis and factorisation do not write into A.
cholmod_sparse wrap(const CscView& A) {
  static Index no_index = 0;  // CHOLMOD wants non-null arrays even with no entries
  static Scalar no_value = 0;
  const Index nnz = A.col_ptr[A.cols];
  cholmod_sparse s{};
  s.nrow = static_cast<size_t>(A.rows);
  s.ncol = static_cast<size_t>(A.cols);
  s.nzmax = static_cast<size_t>(std::max<Index>(nnz, 1));
  s.p = const_cast<Index*>(A.col_ptr);
  s.i = nnz > 0 ? const_cast<Index*>(A.row_index) : &no_index;
  s.x = nnz > 0 ? const_cast<Scalar*>(A.values) : &no_value;
  s.stype = -1;
  s.itype = CHOLMOD_LONG;
  s.xtype = CHOLMOD_REAL;
  s.dtype = CHOLMOD_DOUBLE;
  s.sorted = 1;
  s.packed = 1;
  return s;
}

}  // namespace

struct CholmodFactor::Impl {
  cholmod_common common{};
  cholmod_factor* L = nullptr;
  cholmod_dense* X = nullptr;  // solve2's result and workspace, reused across solves
  cholmod_dense* Y = nullptr;
  cholmod_dense* E = nullptr;
  Index n = 0;
  Index lnz = 0;
  std::vector<Index> col_ptr, row_index;  // the analysed pattern, to check refactor's
  bool valid = false;                     // false after a failed factorisation
  Index failed_column = -1;
  std::mutex mutex;

  explicit Impl(CholmodOrdering ordering) {
    cholmod_l_start(&common);
    common.print = 0;
    common.error_handler = record_error;
    common.supernodal = CHOLMOD_SUPERNODAL;
    switch (ordering) {
      case CholmodOrdering::Default:
        break;
      case CholmodOrdering::Amd:
        common.nmethods = 1;
        common.method[0].ordering = CHOLMOD_AMD;
        break;
      case CholmodOrdering::Metis:
        common.nmethods = 1;
        common.method[0].ordering = CHOLMOD_METIS;
        break;
      case CholmodOrdering::Natural:
        // Postordering would permute the natural order; leading minors keep their meaning.
        common.nmethods = 1;
        common.method[0].ordering = CHOLMOD_NATURAL;
        common.postorder = 0;
        break;
    }
  }

  ~Impl() {
    cholmod_l_free_dense(&X, &common);
    cholmod_l_free_dense(&Y, &common);
    cholmod_l_free_dense(&E, &common);
    cholmod_l_free_factor(&L, &common);
    cholmod_l_finish(&common);
  }

  // Throws for a failed CHOLMOD call (negative status).
  void check(const char* what) const {
    if (common.status >= CHOLMOD_OK) return;
    if (common.status == CHOLMOD_OUT_OF_MEMORY) throw std::bad_alloc();
    throw KinemaError(std::string("CHOLMOD ") + what + " failed: " + cholmod_message);
  }

  void analyse(cholmod_sparse* A) {
    cholmod_message.clear();
    L = cholmod_l_analyze(A, &common);
    if (!L) {
      check("analysis");
      throw KinemaError("CHOLMOD analysis failed: " + cholmod_message);
    }
    lnz = static_cast<Index>(common.lnz);
  }

  void factorize(cholmod_sparse* A) {
    valid = false;
    cholmod_message.clear();
    cholmod_l_factorize(A, L, &common);
    check("factorisation");
    const Index minor = static_cast<Index>(L->minor);
    if (common.status == CHOLMOD_NOT_POSDEF || minor < n) {
      // L->minor counts in the permuted order P A P^T; report the column of A itself.
      const Index* perm = static_cast<const Index*>(L->Perm);
      failed_column = perm ? perm[minor] : minor;
      throw NotPositiveDefinite(
          "A: not positive definite: the Cholesky factorisation met a non-positive pivot at "
          "column " + str(failed_column) + " (pivot " + str(minor) + " of the reordered matrix)",
          failed_column);
    }
    failed_column = -1;
    valid = true;
  }
};

CholmodFactor::CholmodFactor(const CscView& A, CholmodOrdering ordering)
    : impl_(std::make_unique<Impl>(ordering)) {
  check_view(A);
  Impl& m = *impl_;
  m.n = A.cols;
  const Index nnz = A.col_ptr[m.n];
  m.col_ptr.assign(A.col_ptr, A.col_ptr + m.n + 1);
  m.row_index.assign(A.row_index, A.row_index + nnz);
  cholmod_sparse s = wrap(A);
  m.analyse(&s);
  m.factorize(&s);
}

CholmodFactor::~CholmodFactor() = default;
CholmodFactor::CholmodFactor(CholmodFactor&&) noexcept = default;
CholmodFactor& CholmodFactor::operator=(CholmodFactor&&) noexcept = default;

void CholmodFactor::refactor(const CscView& A) {
  Impl& m = *impl_;
  std::lock_guard<std::mutex> lock(m.mutex);
  check_view(A);
  if (A.cols != m.n)
    throw InvalidArgument("A: expected the factorised size " + str(m.n) + " x " + str(m.n) +
                          ", got " + str(A.rows) + " x " + str(A.cols));
  for (Index j = 0; j < m.n; ++j) {
    const Index begin = A.col_ptr[j], end = A.col_ptr[j + 1];
    if (begin != m.col_ptr[j] || end != m.col_ptr[j + 1] ||
        !std::equal(A.row_index + begin, A.row_index + end, m.row_index.begin() + begin))
      throw InvalidArgument("A: sparsity pattern differs from the factorised matrix's (first in "
                            "column " + str(j) + "); refactor needs the same pattern, "
                            "factorise the new matrix instead");
  }
  cholmod_sparse s = wrap(A);
  m.factorize(&s);
}

void CholmodFactor::solve(const Scalar* b, Scalar* x, Index nrhs) const {
  Impl& m = *impl_;
  std::lock_guard<std::mutex> lock(m.mutex);
  if (!m.valid)
    throw KinemaError("solve: the last factorisation failed (not positive definite at column " +
                      str(m.failed_column) + "); refactor a positive definite matrix first");
  if (nrhs < 0) throw InvalidArgument("nrhs: expected >= 0, got " + str(nrhs));
  if (nrhs == 0) return;
  cholmod_dense B{};
  B.nrow = static_cast<size_t>(m.n);
  B.ncol = static_cast<size_t>(nrhs);
  B.nzmax = B.nrow * B.ncol;
  B.d = B.nrow;
  B.x = const_cast<Scalar*>(b);  // read only
  B.xtype = CHOLMOD_REAL;
  B.dtype = CHOLMOD_DOUBLE;
  cholmod_message.clear();
  cholmod_l_solve2(CHOLMOD_A, m.L, &B, nullptr, &m.X, nullptr, &m.Y, &m.E, &m.common);
  m.check("solve");
  const Scalar* result = static_cast<const Scalar*>(m.X->x);
  std::copy(result, result + m.n * nrhs, x);
}

Index CholmodFactor::size() const { return impl_->n; }

Index CholmodFactor::factor_nonzeros() const { return impl_->lnz; }

bool CholmodFactor::is_supernodal() const { return impl_->L->is_super != 0; }

const Index* CholmodFactor::permutation() const {
  return static_cast<const Index*>(impl_->L->Perm);
}

Scalar CholmodFactor::log_determinant() const {
  Impl& m = *impl_;
  std::lock_guard<std::mutex> lock(m.mutex);
  if (!m.valid)
    throw KinemaError("log_determinant: the last factorisation failed (not positive definite)");
  // Supernode s holds columns super[s] .. super[s+1]-1 of L as a dense column-major block of
  // pi[s+1]-pi[s] rows starting at x[px[s]]; its leading square is the diagonal block.
  const cholmod_factor* L = m.L;
  const auto* super = static_cast<const Index*>(L->super);
  const auto* pi = static_cast<const Index*>(L->pi);
  const auto* px = static_cast<const Index*>(L->px);
  const auto* x = static_cast<const Scalar*>(L->x);
  Scalar sum = 0;
  for (size_t s = 0; s < L->nsuper; ++s) {
    const Index rows = pi[s + 1] - pi[s];
    for (Index j = 0; j < super[s + 1] - super[s]; ++j) sum += std::log(x[px[s] + j * rows + j]);
  }
  return 2 * sum;
}

}  // namespace kinema
