#include "linalg/cholmod_factor.h"

#include <cholmod.h>

#include <algorithm>
#include <limits>
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
template <class J>
void check_view(const BasicCscView<J>& A) {
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

// CHOLMOD comes in two index widths: cholmod_* (int) and cholmod_l_* (SuiteSparse_long). The
// int interface moves half the index bytes through the symbolic analysis and the supernodal
// assembly (about a third less analysis time at 1024^2, and it is what scikit-sparse calls for
// scipy's int32 matrices), so it is used whenever the matrix and its factor fit in int.
template <class I>
struct Api;

template <>
struct Api<int> {
  static constexpr int itype = CHOLMOD_INT;
  static void start(cholmod_common* c) { cholmod_start(c); }
  static void finish(cholmod_common* c) { cholmod_finish(c); }
  static cholmod_factor* analyze(cholmod_sparse* A, cholmod_common* c) {
    return cholmod_analyze(A, c);
  }
  static void factorize(cholmod_sparse* A, cholmod_factor* L, cholmod_common* c) {
    cholmod_factorize(A, L, c);
  }
  static void solve2(cholmod_factor* L, cholmod_dense* B, cholmod_dense** X, cholmod_dense** Y,
                     cholmod_dense** E, cholmod_common* c) {
    cholmod_solve2(CHOLMOD_A, L, B, nullptr, X, nullptr, Y, E, c);
  }
  static void free_dense(cholmod_dense** X, cholmod_common* c) { cholmod_free_dense(X, c); }
  static void free_factor(cholmod_factor** L, cholmod_common* c) { cholmod_free_factor(L, c); }
};

template <>
struct Api<SuiteSparse_long> {
  static constexpr int itype = CHOLMOD_LONG;
  static void start(cholmod_common* c) { cholmod_l_start(c); }
  static void finish(cholmod_common* c) { cholmod_l_finish(c); }
  static cholmod_factor* analyze(cholmod_sparse* A, cholmod_common* c) {
    return cholmod_l_analyze(A, c);
  }
  static void factorize(cholmod_sparse* A, cholmod_factor* L, cholmod_common* c) {
    cholmod_l_factorize(A, L, c);
  }
  static void solve2(cholmod_factor* L, cholmod_dense* B, cholmod_dense** X, cholmod_dense** Y,
                     cholmod_dense** E, cholmod_common* c) {
    cholmod_l_solve2(CHOLMOD_A, L, B, nullptr, X, nullptr, Y, E, c);
  }
  static void free_dense(cholmod_dense** X, cholmod_common* c) { cholmod_l_free_dense(X, c); }
  static void free_factor(cholmod_factor** L, cholmod_common* c) { cholmod_l_free_factor(L, c); }
};

// Thrown inside the int backend when the factor would not fit in int; the long one takes over.
struct TooLargeForInt {};

}  // namespace

// One CHOLMOD factorisation in index type I. It keeps its own copy of the analysed pattern in
// I (the array CHOLMOD reads, and the reference refactor checks against); values are borrowed
// for the duration of a call.
struct CholmodFactor::Impl {
  virtual ~Impl() = default;
  virtual void factorize(const Scalar* values) = 0;  // of the analysed pattern
  virtual bool same_pattern(const CscView& A, Index* first_difference) const = 0;
  virtual bool same_pattern(const CscView32& A, Index* first_difference) const = 0;
  virtual void solve(const Scalar* b, Scalar* x, Index nrhs) = 0;
  virtual Scalar log_determinant() const = 0;
  virtual bool is_supernodal() const = 0;
  virtual int index_bits() const = 0;

  Index n = 0;
  Index lnz = 0;
  std::vector<Index> perm;  // fill-reducing permutation, as Index whatever I is
  bool valid = false;       // false after a failed factorisation
  Index failed_column = -1;
  std::mutex mutex;
};

namespace {

template <class I>
class Backend final : public CholmodFactor::Impl {
 public:
  template <class J>
  Backend(const BasicCscView<J>& A, CholmodOrdering ordering) {
    Api<I>::start(&common_);
    common_.print = 0;
    common_.error_handler = record_error;
    common_.supernodal = CHOLMOD_SUPERNODAL;
    switch (ordering) {
      case CholmodOrdering::Default:
        break;
      case CholmodOrdering::Amd:
        common_.nmethods = 1;
        common_.method[0].ordering = CHOLMOD_AMD;
        break;
      case CholmodOrdering::Metis:
        common_.nmethods = 1;
        common_.method[0].ordering = CHOLMOD_METIS;
        break;
      case CholmodOrdering::Natural:
        // Postordering would permute the natural order; leading minors keep their meaning.
        common_.nmethods = 1;
        common_.method[0].ordering = CHOLMOD_NATURAL;
        common_.postorder = 0;
        break;
    }
    n = A.cols;
    const Index nnz = A.col_ptr[n];
    col_ptr_.assign(A.col_ptr, A.col_ptr + n + 1);
    row_index_.assign(A.row_index, A.row_index + nnz);
  }

  // Fill-reducing ordering and symbolic factorisation (separate from the constructor, so that
  // a throw still runs the destructor).
  void analyse(const Scalar* values) {
    cholmod_sparse s = wrap(values);
    cholmod_message.clear();
    L_ = Api<I>::analyze(&s, &common_);
    if (!L_) {
      if (common_.status == CHOLMOD_TOO_LARGE && std::is_same_v<I, int>) throw TooLargeForInt{};
      check("analysis");
      throw KinemaError("CHOLMOD analysis failed: " + cholmod_message);
    }
    lnz = static_cast<Index>(common_.lnz);
    const I* p = static_cast<const I*>(L_->Perm);
    perm.assign(p, p + n);
  }

  ~Backend() override {
    Api<I>::free_dense(&X_, &common_);
    Api<I>::free_dense(&Y_, &common_);
    Api<I>::free_dense(&E_, &common_);
    Api<I>::free_factor(&L_, &common_);
    Api<I>::finish(&common_);
  }

  void factorize(const Scalar* values) override {
    valid = false;
    cholmod_sparse s = wrap(values);
    cholmod_message.clear();
    Api<I>::factorize(&s, L_, &common_);
    check("factorisation");
    const Index minor = static_cast<Index>(L_->minor);
    if (common_.status == CHOLMOD_NOT_POSDEF || minor < n) {
      // L->minor counts in the permuted order P A P^T; report the column of A itself.
      failed_column = perm[minor];
      throw NotPositiveDefinite(
          "A: not positive definite: the Cholesky factorisation met a non-positive pivot at "
          "column " + str(failed_column) + " (pivot " + str(minor) + " of the reordered matrix)",
          failed_column);
    }
    failed_column = -1;
    valid = true;
  }

  bool same_pattern(const CscView& A, Index* first_difference) const override {
    return same_pattern_as(A, first_difference);
  }
  bool same_pattern(const CscView32& A, Index* first_difference) const override {
    return same_pattern_as(A, first_difference);
  }

  template <class J>
  bool same_pattern_as(const BasicCscView<J>& A, Index* first_difference) const {
    for (Index j = 0; j < n; ++j) {
      const Index begin = A.col_ptr[j], end = A.col_ptr[j + 1];
      if (begin != col_ptr_[j] || end != col_ptr_[j + 1] ||
          !std::equal(A.row_index + begin, A.row_index + end, row_index_.begin() + begin)) {
        *first_difference = j;
        return false;
      }
    }
    return true;
  }

  void solve(const Scalar* b, Scalar* x, Index nrhs) override {
    cholmod_dense B{};
    B.nrow = static_cast<size_t>(n);
    B.ncol = static_cast<size_t>(nrhs);
    B.nzmax = B.nrow * B.ncol;
    B.d = B.nrow;
    B.x = const_cast<Scalar*>(b);  // read only
    B.xtype = CHOLMOD_REAL;
    B.dtype = CHOLMOD_DOUBLE;
    cholmod_message.clear();
    Api<I>::solve2(L_, &B, &X_, &Y_, &E_, &common_);
    check("solve");
    const Scalar* result = static_cast<const Scalar*>(X_->x);
    std::copy(result, result + n * nrhs, x);
  }

  Scalar log_determinant() const override {
    // Supernode s holds columns super[s] .. super[s+1]-1 of L as a dense column-major block of
    // pi[s+1]-pi[s] rows starting at x[px[s]]; its leading square is the diagonal block.
    const auto* super = static_cast<const I*>(L_->super);
    const auto* pi = static_cast<const I*>(L_->pi);
    const auto* px = static_cast<const I*>(L_->px);
    const auto* x = static_cast<const Scalar*>(L_->x);
    Scalar sum = 0;
    for (size_t s = 0; s < L_->nsuper; ++s) {
      const Index rows = pi[s + 1] - pi[s];
      for (Index j = 0; j < super[s + 1] - super[s]; ++j)
        sum += std::log(x[px[s] + j * rows + j]);
    }
    return 2 * sum;
  }

  bool is_supernodal() const override { return L_->is_super != 0; }
  int index_bits() const override { return 8 * static_cast<int>(sizeof(I)); }

 private:
  // Throws for a failed CHOLMOD call (negative status).
  void check(const char* what) const {
    if (common_.status >= CHOLMOD_OK) return;
    if (common_.status == CHOLMOD_OUT_OF_MEMORY) throw std::bad_alloc();
    throw KinemaError(std::string("CHOLMOD ") + what + " failed: " + cholmod_message);
  }

  // The stored pattern with borrowed values, as a CHOLMOD matrix. stype = -1: CHOLMOD reads
  // only the lower triangle. Neither analysis nor factorisation writes into it.
  cholmod_sparse wrap(const Scalar* values) const {
    static Scalar no_value = 0;  // CHOLMOD wants non-null arrays even with no entries
    const size_t nnz = row_index_.size();
    cholmod_sparse s{};
    s.nrow = s.ncol = static_cast<size_t>(n);
    s.nzmax = std::max<size_t>(nnz, 1);
    s.p = const_cast<I*>(col_ptr_.data());
    s.i = nnz > 0 ? const_cast<I*>(row_index_.data()) : const_cast<I*>(&no_index_);
    s.x = nnz > 0 ? const_cast<Scalar*>(values) : &no_value;
    s.stype = -1;
    s.itype = Api<I>::itype;
    s.xtype = CHOLMOD_REAL;
    s.dtype = CHOLMOD_DOUBLE;
    s.sorted = 1;
    s.packed = 1;
    return s;
  }

  cholmod_common common_{};
  cholmod_factor* L_ = nullptr;
  cholmod_dense* X_ = nullptr;  // solve2's result and workspace, reused across solves
  cholmod_dense* Y_ = nullptr;
  cholmod_dense* E_ = nullptr;
  std::vector<I> col_ptr_, row_index_;
  I no_index_ = 0;
};

template <class J>
bool fits_int(const BasicCscView<J>& A) {
  return A.col_ptr[A.cols] < std::numeric_limits<int>::max() &&
         A.cols < std::numeric_limits<int>::max();
}

template <class J>
std::unique_ptr<CholmodFactor::Impl> make_backend(const BasicCscView<J>& A, CholmodOrdering ordering,
                                                  CholmodIndexWidth width) {
  if (width != CholmodIndexWidth::Long) {
    const bool fits = fits_int(A);
    if (!fits && width == CholmodIndexWidth::Int)
      throw InvalidArgument("A: too large for CHOLMOD's int interface (" + str(A.cols) +
                            " columns, " + str(A.col_ptr[A.cols]) + " entries)");
    try {
      if (fits) {
        auto backend = std::make_unique<Backend<int>>(A, ordering);
        backend->analyse(A.values);
        return backend;
      }
    } catch (const TooLargeForInt&) {
      // the factor of an int-sized matrix may still overflow int: analyse again in long
      if (width == CholmodIndexWidth::Int)
        throw InvalidArgument("A: its Cholesky factor is too large for CHOLMOD's int interface");
    }
  }
  auto backend = std::make_unique<Backend<SuiteSparse_long>>(A, ordering);
  backend->analyse(A.values);
  return backend;
}

// The two index widths of the input share one body.
template <class J>
std::unique_ptr<CholmodFactor::Impl> factorise(const BasicCscView<J>& A, CholmodOrdering ordering,
                                               CholmodIndexWidth width) {
  check_view(A);
  auto impl = make_backend(A, ordering, width);
  impl->factorize(A.values);
  return impl;
}

template <class J>
void refactorise(CholmodFactor::Impl& m, const BasicCscView<J>& A) {
  std::lock_guard<std::mutex> lock(m.mutex);
  check_view(A);
  if (A.cols != m.n)
    throw InvalidArgument("A: expected the factorised size " + str(m.n) + " x " + str(m.n) +
                          ", got " + str(A.rows) + " x " + str(A.cols));
  Index j = 0;
  if (!m.same_pattern(A, &j))
    throw InvalidArgument("A: sparsity pattern differs from the factorised matrix's (first in "
                          "column " + str(j) + "); refactor needs the same pattern, "
                          "factorise the new matrix instead");
  m.factorize(A.values);
}

}  // namespace

CholmodFactor::CholmodFactor(const CscView& A, CholmodOrdering ordering, CholmodIndexWidth width)
    : impl_(factorise(A, ordering, width)) {}
CholmodFactor::CholmodFactor(const CscView32& A, CholmodOrdering ordering, CholmodIndexWidth width)
    : impl_(factorise(A, ordering, width)) {}

CholmodFactor::~CholmodFactor() = default;
CholmodFactor::CholmodFactor(CholmodFactor&&) noexcept = default;
CholmodFactor& CholmodFactor::operator=(CholmodFactor&&) noexcept = default;

void CholmodFactor::refactor(const CscView& A) { refactorise(*impl_, A); }
void CholmodFactor::refactor(const CscView32& A) { refactorise(*impl_, A); }

void CholmodFactor::solve(const Scalar* b, Scalar* x, Index nrhs) const {
  Impl& m = *impl_;
  std::lock_guard<std::mutex> lock(m.mutex);
  if (!m.valid)
    throw KinemaError("solve: the last factorisation failed (not positive definite at column " +
                      str(m.failed_column) + "); refactor a positive definite matrix first");
  if (nrhs < 0) throw InvalidArgument("nrhs: expected >= 0, got " + str(nrhs));
  if (nrhs == 0) return;
  m.solve(b, x, nrhs);
}

Index CholmodFactor::size() const { return impl_->n; }

Index CholmodFactor::factor_nonzeros() const { return impl_->lnz; }

bool CholmodFactor::is_supernodal() const { return impl_->is_supernodal(); }

int CholmodFactor::index_bits() const { return impl_->index_bits(); }

const Index* CholmodFactor::permutation() const { return impl_->perm.data(); }

Scalar CholmodFactor::log_determinant() const {
  Impl& m = *impl_;
  std::lock_guard<std::mutex> lock(m.mutex);
  if (!m.valid)
    throw KinemaError("log_determinant: the last factorisation failed (not positive definite)");
  return m.log_determinant();
}

}  // namespace kinema
